/* hwsim_ffi_test.c: the C side of tests/hwsim_ffi.rs. Reads a scene file and a golden vectors
 * file (emc-hwsim's vectors format), configures the unit and emc-core's encoder through the C
 * ABI, and checks every code and the cycle each code leaves the unit; also the error paths.
 * Usage: hwsim_ffi_test LAYOUT ROUTING SCENE VECTORS; prints "C PASS n" or exits non-zero. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "emc_hwsim.h"

static float f32(uint32_t bits) { float f; memcpy(&f, &bits, sizeof f); return f; }

/* Read lines "6×f32-hex code-hex in out" (comments '#'); codes/cycles optional outputs. */
static size_t read_file(const char *path, EmcAabb **boxes, uint64_t **codes, long **in, long **out) {
  FILE *f = fopen(path, "r");
  if (!f) { fprintf(stderr, "cannot open %s\n", path); exit(2); }
  size_t cap = 1024, n = 0;
  *boxes = malloc(cap * sizeof **boxes); *codes = malloc(cap * sizeof **codes);
  *in = malloc(cap * sizeof **in); *out = malloc(cap * sizeof **out);
  char line[512];
  while (fgets(line, sizeof line, f)) {
    if (line[0] == '#' || line[0] == '\n') continue;
    unsigned int b[6]; unsigned long long c; long ci, co;
    if (sscanf(line, "%x %x %x %x %x %x %llx %ld %ld", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &c, &ci, &co) != 9) {
      fprintf(stderr, "%s: malformed line %zu\n", path, n + 1); exit(2);
    }
    if (n == cap) {
      cap *= 2;
      *boxes = realloc(*boxes, cap * sizeof **boxes); *codes = realloc(*codes, cap * sizeof **codes);
      *in = realloc(*in, cap * sizeof **in); *out = realloc(*out, cap * sizeof **out);
    }
    for (int k = 0; k < 3; k++) { (*boxes)[n].min[k] = f32(b[k]); (*boxes)[n].max[k] = f32(b[3 + k]); }
    (*codes)[n] = c; (*in)[n] = ci; (*out)[n] = co; n++;
  }
  fclose(f);
  return n;
}

#define CHECK(cond, ...) do { if (!(cond)) { fprintf(stderr, __VA_ARGS__); fputc('\n', stderr); return 1; } } while (0)

int main(int argc, char **argv) {
  if (argc != 5) { fprintf(stderr, "usage: %s LAYOUT ROUTING SCENE VECTORS\n", argv[0]); return 2; }
  EmcAabb *scene, *vb; uint64_t *sc, *gold; long *si, *so, *vin, *vout;
  size_t ns = read_file(argv[3], &scene, &sc, &si, &so);
  size_t nv = read_file(argv[4], &vb, &gold, &vin, &vout);
  EmcUnit *u = NULL; EmcEncoder *e = NULL;
  EmcStatus s = emc_unit_new(argv[1], scene, ns, (uint32_t)atoi(argv[2]), &u);
  CHECK(s == EMC_OK, "emc_unit_new: %s", emc_status_str(s));
  s = emc_encoder_new(argv[1], scene, ns, &e);
  CHECK(s == EMC_OK, "emc_encoder_new: %s", emc_status_str(s));
  uint64_t *cu = malloc(nv * sizeof *cu), *ce = malloc(nv * sizeof *ce);
  CHECK(emc_unit_encode(u, vb, nv, cu) == EMC_OK, "emc_unit_encode");
  CHECK(emc_encoder_encode(e, vb, nv, ce) == EMC_OK, "emc_encoder_encode");
  uint32_t depth = 0, ii = 0;
  CHECK(emc_unit_latency(u, &depth, &ii) == EMC_OK, "emc_unit_latency");
  for (size_t i = 0; i < nv; i++) {
    CHECK(cu[i] == gold[i], "vector %zu: unit code %016llx, golden %016llx", i, (unsigned long long)cu[i], (unsigned long long)gold[i]);
    CHECK(ce[i] == gold[i], "vector %zu: encoder code %016llx, golden %016llx", i, (unsigned long long)ce[i], (unsigned long long)gold[i]);
    /* One box per II cycles; each code leaves depth cycles after its box entered. */
    CHECK(vin[i] == (long)(i * ii) && vout[i] == vin[i] + (long)depth, "vector %zu: cycles %ld %ld, model depth %u II %u", i, vin[i], vout[i], depth, ii);
  }
  uint64_t cycles = 0;
  CHECK(emc_unit_cycles(u, nv, 25.6, 1.0, 100.0, &cycles) == EMC_OK && cycles > nv, "emc_unit_cycles");
  /* Error paths: status codes, never a crash. */
  EmcUnit *bad = NULL;
  CHECK(emc_unit_new("no-such-layout", scene, ns, 0, &bad) == EMC_BAD_LAYOUT && bad == NULL, "bad layout");
  CHECK(emc_unit_new(argv[1], scene, 0, 0, &bad) == EMC_BAD_SCENE, "empty scene");
  CHECK(emc_unit_new(argv[1], scene, ns, 9, &bad) == EMC_BAD_CONFIG, "bad routing");
  CHECK(emc_unit_new(NULL, scene, ns, 0, &bad) == EMC_NULL_POINTER, "null layout");
  CHECK(emc_unit_encode(NULL, vb, nv, cu) == EMC_NULL_POINTER, "null unit");
  CHECK(emc_unit_encode(u, NULL, nv, cu) == EMC_NULL_POINTER, "null boxes");
  CHECK(emc_unit_cycles(u, nv, -1.0, 1.0, 100.0, &cycles) == EMC_BAD_CONFIG, "bad bandwidth");
  EmcAabb nan_box = scene[0]; nan_box.min[0] = f32(0x7fc00000u);
  EmcEncoder *bad_e = NULL;
  CHECK(emc_encoder_new(argv[1], &nan_box, 1, &bad_e) == EMC_BAD_SCENE && bad_e == NULL, "nan scene");
  CHECK(emc_encoder_encode(e, vb, nv, NULL) == EMC_NULL_POINTER, "null codes");
  emc_unit_free(u);
  emc_unit_free(NULL);
  emc_encoder_free(e);
  printf("C PASS %zu vectors, depth %u, II %u, %llu cycles at 25.6 GB/s\n", nv, depth, ii, (unsigned long long)cycles);
  free(scene); free(sc); free(si); free(so); free(vb); free(gold); free(vin); free(vout); free(cu); free(ce);
  return 0;
}
