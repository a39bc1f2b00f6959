//! What this CPU can do and how fast, read once with CPUID (works in `no_std`).
//! "BMI2 present" does not mean "use pdep": AMD and Hygon before family 0x19 (Excavator, Zen 1,
//! Zen+, Zen 2, Dhyana) run `pdep`/`pext` in microcode, 20 to 290 cycles each.

/// The CPU facts dispatch decides on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CpuInfo {
    /// Vendor string (`AuthenticAMD`, `GenuineIntel`, …); empty off x86.
    pub vendor: [u8; 12],
    /// Display family (base + extended when base is 0xF).
    pub family: u32,
    /// Display model.
    pub model: u32,
    /// BMI2 (`pdep`/`pext`) present.
    pub bmi2: bool,
    /// AVX2 present and enabled by the OS (XCR0 saves YMM state).
    pub avx2: bool,
}

impl CpuInfo {
    /// The vendor as text.
    pub fn vendor_str(&self) -> &str {
        core::str::from_utf8(&self.vendor)
            .unwrap_or("unknown")
            .trim_end_matches('\0')
    }

    /// True when `pdep` is a fast (single-µop) instruction here.
    pub fn fast_pdep(&self) -> bool {
        if !self.bmi2 {
            return false;
        }
        let amd_like = &self.vendor == b"AuthenticAMD" || &self.vendor == b"HygonGenuine";
        !(amd_like && self.family < 0x19)
    }

    /// One line saying whether pdep is used and why.
    pub fn pdep_reason(&self) -> &'static str {
        if !self.bmi2 {
            "no BMI2 on this CPU"
        } else if self.fast_pdep() {
            "BMI2 present and pdep is a fast single instruction on this CPU"
        } else {
            "BMI2 present but pdep is microcoded on AMD/Hygon before family 0x19 (20-290 cycles)"
        }
    }
}

/// The answers of this module's CPUID reads, kept after the first call: CPUID traps to the
/// hypervisor in a virtual machine (an encoder's set-up, which asks several times, took
/// 0.11 ms on a cloud Zen 5, a tenth of encoding a million boxes). Atomics only, so `no_std`
/// keeps it; threads racing on the first call compute and store the same values.
#[cfg(target_arch = "x86_64")]
mod cache {
    use core::sync::atomic::{AtomicU32, Ordering};

    /// Set in `FLAGS` once the other words hold the answer.
    const READY: u32 = 1 << 31;
    const BMI2: u32 = 1 << 0;
    const AVX2: u32 = 1 << 1;
    const AVX512_KNOWN: u32 = 1 << 2;
    const AVX512: u32 = 1 << 3;
    const SHUFFLE_KNOWN: u32 = 1 << 4;
    const SHUFFLE: u32 = 1 << 5;

    static VENDOR: [AtomicU32; 3] = [AtomicU32::new(0), AtomicU32::new(0), AtomicU32::new(0)];
    static FAMILY: AtomicU32 = AtomicU32::new(0);
    static MODEL: AtomicU32 = AtomicU32::new(0);
    static FLAGS: AtomicU32 = AtomicU32::new(0);
    /// The AVX-512 answers, each with its own "known" bit.
    static EXTRA: AtomicU32 = AtomicU32::new(0);

    pub(super) fn info(read: impl FnOnce() -> super::CpuInfo) -> super::CpuInfo {
        let flags = FLAGS.load(Ordering::Acquire);
        if flags & READY != 0 {
            let mut vendor = [0u8; 12];
            for (i, w) in VENDOR.iter().enumerate() {
                vendor[4 * i..4 * i + 4].copy_from_slice(&w.load(Ordering::Relaxed).to_le_bytes());
            }
            return super::CpuInfo {
                vendor,
                family: FAMILY.load(Ordering::Relaxed),
                model: MODEL.load(Ordering::Relaxed),
                bmi2: flags & BMI2 != 0,
                avx2: flags & AVX2 != 0,
            };
        }
        let info = read();
        for (i, w) in VENDOR.iter().enumerate() {
            let b = &info.vendor[4 * i..4 * i + 4];
            w.store(
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                Ordering::Relaxed,
            );
        }
        FAMILY.store(info.family, Ordering::Relaxed);
        MODEL.store(info.model, Ordering::Relaxed);
        let bits = READY | if info.bmi2 { BMI2 } else { 0 } | if info.avx2 { AVX2 } else { 0 };
        FLAGS.store(bits, Ordering::Release);
        info
    }

    fn extra(known: u32, yes: u32, read: impl FnOnce() -> bool) -> bool {
        let e = EXTRA.load(Ordering::Relaxed);
        if e & known != 0 {
            return e & yes != 0;
        }
        let v = read();
        EXTRA.fetch_or(known | if v { yes } else { 0 }, Ordering::Relaxed);
        v
    }

    pub(super) fn avx512(read: impl FnOnce() -> bool) -> bool {
        extra(AVX512_KNOWN, AVX512, read)
    }

    pub(super) fn shuffle(read: impl FnOnce() -> bool) -> bool {
        extra(SHUFFLE_KNOWN, SHUFFLE, read)
    }
}

/// The CPU facts, read with CPUID on the first call and kept (see `cache`).
#[cfg(target_arch = "x86_64")]
pub fn detect() -> CpuInfo {
    cache::info(read_cpu)
}

/// Read the CPU: a handful of CPUID instructions.
#[cfg(target_arch = "x86_64")]
fn read_cpu() -> CpuInfo {
    use core::arch::x86_64::{__cpuid, __cpuid_count};
    let l0 = __cpuid(0);
    let mut vendor = [0u8; 12];
    vendor[0..4].copy_from_slice(&l0.ebx.to_le_bytes());
    vendor[4..8].copy_from_slice(&l0.edx.to_le_bytes());
    vendor[8..12].copy_from_slice(&l0.ecx.to_le_bytes());
    let max_leaf = l0.eax;
    let l1 = __cpuid(1);
    let base_family = (l1.eax >> 8) & 0xF;
    let ext_family = (l1.eax >> 20) & 0xFF;
    let family = if base_family == 0xF {
        base_family + ext_family
    } else {
        base_family
    };
    let base_model = (l1.eax >> 4) & 0xF;
    let ext_model = (l1.eax >> 16) & 0xF;
    let model = if base_family == 0x6 || base_family == 0xF {
        (ext_model << 4) | base_model
    } else {
        base_model
    };
    let (bmi2, avx2_bit) = if max_leaf >= 7 {
        let l7 = __cpuid_count(7, 0);
        ((l7.ebx >> 8) & 1 == 1, (l7.ebx >> 5) & 1 == 1)
    } else {
        (false, false)
    };
    let osxsave = (l1.ecx >> 27) & 1 == 1;
    let avx = (l1.ecx >> 28) & 1 == 1;
    let avx2 = avx2_bit && avx && osxsave && os_saves_ymm();
    CpuInfo {
        vendor,
        family,
        model,
        bmi2,
        avx2,
    }
}

#[cfg(target_arch = "x86_64")]
fn os_saves_ymm() -> bool {
    xcr0() & 0b110 == 0b110
}

/// XCR0, the state components the OS saves; only called after CPUID reported OSXSAVE.
#[cfg(target_arch = "x86_64")]
fn xcr0() -> u64 {
    #[target_feature(enable = "xsave")]
    unsafe fn read() -> u64 {
        // SAFETY: the caller checked OSXSAVE, so XGETBV with register 0 is defined.
        unsafe { core::arch::x86_64::_xgetbv(0) }
    }
    // SAFETY: only called after CPUID reported OSXSAVE, which implies XGETBV is usable.
    unsafe { read() }
}

/// AVX-512 F, DQ, BW and VL present and enabled by the OS: CPUID leaf 7 EBX bits 16 (F),
/// 17 (DQ), 30 (BW) and 31 (VL), plus XCR0 saving SSE/AVX state (bits 1-2) and the opmask
/// and ZMM state (bits 5-7). Read with CPUID on the first call and kept.
#[cfg(target_arch = "x86_64")]
pub fn has_avx512() -> bool {
    cache::avx512(read_avx512)
}

#[cfg(target_arch = "x86_64")]
fn read_avx512() -> bool {
    use core::arch::x86_64::{__cpuid, __cpuid_count};
    if __cpuid(0).eax < 7 {
        return false;
    }
    let osxsave = (__cpuid(1).ecx >> 27) & 1 == 1;
    let ebx = __cpuid_count(7, 0).ebx;
    let need = (1 << 16) | (1 << 17) | (1 << 30) | (1 << 31);
    osxsave && ebx & need == need && xcr0() & 0b1110_0110 == 0b1110_0110
}

/// Off x86_64 there is no AVX-512.
#[cfg(not(target_arch = "x86_64"))]
pub fn has_avx512() -> bool {
    false
}

/// [`has_avx512`] plus VBMI (`vpermb`, leaf 7 ECX bit 1) and BITALG (`vpshufbitqmb`, ECX
/// bit 12): what the bit-shuffle expansion of the batch pipeline needs.
pub fn has_avx512_bit_shuffle() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        cache::shuffle(|| {
            let ecx = core::arch::x86_64::__cpuid_count(7, 0).ecx;
            has_avx512() && ecx & (1 << 1) != 0 && ecx & (1 << 12) != 0
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Off x86_64 there is no `pdep` and no AVX2.
#[cfg(not(target_arch = "x86_64"))]
pub fn detect() -> CpuInfo {
    CpuInfo {
        vendor: [0; 12],
        family: 0,
        model: 0,
        bmi2: false,
        avx2: false,
    }
}

/// BMI2 present (correctness only, not speed).
#[inline]
pub fn has_bmi2() -> bool {
    detect().bmi2
}

/// BMI2 present and fast.
#[inline]
pub fn fast_pdep() -> bool {
    detect().fast_pdep()
}

/// AVX2 present and enabled by the OS.
#[inline]
pub fn has_avx2() -> bool {
    detect().avx2
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    #[test]
    fn the_kept_answers_equal_fresh_reads() {
        // The first call reads and keeps, the later ones return what was kept: both must be
        // what the CPU says now.
        for _ in 0..3 {
            assert_eq!(detect(), read_cpu());
            assert_eq!(has_avx512(), read_avx512());
        }
        let ecx = core::arch::x86_64::__cpuid_count(7, 0).ecx;
        let shuffle = read_avx512() && ecx & (1 << 1) != 0 && ecx & (1 << 12) != 0;
        assert_eq!(has_avx512_bit_shuffle(), shuffle);
        assert_eq!(has_avx512_bit_shuffle(), shuffle);
    }
}
