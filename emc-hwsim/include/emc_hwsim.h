/* emc_hwsim.h: the C ABI of emc-hwsim, the golden model of the EMC unit (src/ffi.rs).
 * Link with libemc_hwsim.a (plus -lpthread -ldl -lm) or libemc_hwsim.so. Kept equal to the
 * Rust signatures by tests/hwsim_ffi.rs; no call unwinds into C (status EMC_PANIC instead). */
#ifndef EMC_HWSIM_H
#define EMC_HWSIM_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

typedef enum EmcStatus {
  EMC_OK = 0,
  EMC_NULL_POINTER = 1,
  EMC_BAD_LAYOUT = 2,
  EMC_BAD_SCENE = 3,
  EMC_BAD_CONFIG = 4,
  EMC_PANIC = 5
} EmcStatus;

typedef struct EmcAabb {
  float min[3];
  float max[3];
} EmcAabb;

typedef struct EmcEncoder EmcEncoder;
typedef struct EmcUnit EmcUnit;

EmcStatus emc_encoder_new(const char *layout, const EmcAabb *boxes, size_t n, EmcEncoder **out);
void emc_encoder_free(EmcEncoder *e);
EmcStatus emc_encoder_encode(const EmcEncoder *e, const EmcAabb *boxes, size_t n, uint64_t *codes);
EmcStatus emc_unit_new(const char *layout, const EmcAabb *boxes, size_t n, uint32_t routing, EmcUnit **out);
void emc_unit_free(EmcUnit *u);
EmcStatus emc_unit_encode(const EmcUnit *u, const EmcAabb *boxes, size_t n, uint64_t *codes);
EmcStatus emc_unit_latency(const EmcUnit *u, uint32_t *depth, uint32_t *ii);
EmcStatus emc_unit_cycles(const EmcUnit *u, uint64_t n, double bandwidth_gbps, double clock_ghz, double latency_ns, uint64_t *cycles);
const char *emc_status_str(uint32_t s);

#ifdef __cplusplus
}
#endif

#endif /* EMC_HWSIM_H */
