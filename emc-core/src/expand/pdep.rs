//! BMI2 `pdep`/`pext` with one mask per channel (x86_64 only). One instruction per channel on
//! CPUs where it is fast; microcoded (tens to hundreds of cycles) on AMD before family 0x19,
//! which is why dispatch only picks it where [`crate::cpu::fast_pdep`] says so.

#![cfg(target_arch = "x86_64")]

use core::arch::x86_64::{_pdep_u64, _pext_u64};

use crate::layout::Layout;

/// The `pdep` expander of one layout. Holding one proves BMI2 is present.
#[derive(Clone, Copy, Debug)]
pub struct Pdep {
    masks: [u64; 4],
}

impl Pdep {
    /// Build for a layout, or `None` when the CPU lacks BMI2.
    pub fn new(layout: &Layout) -> Option<Pdep> {
        if crate::cpu::has_bmi2() {
            Some(Pdep {
                masks: layout.masks(),
            })
        } else {
            None
        }
    }

    /// The per-channel masks (x, y, z, s).
    #[inline]
    pub fn masks(&self) -> [u64; 4] {
        self.masks
    }

    /// Interleave channel values (x, y, z, s); bits above each channel's width are ignored.
    #[inline]
    pub fn expand(&self, q: [u64; 4]) -> u64 {
        // SAFETY: a `Pdep` exists only if `has_bmi2()` returned true (see `new`).
        unsafe { expand_bmi2(&self.masks, q) }
    }

    /// Split a code back into channel values.
    #[inline]
    pub fn compact(&self, code: u64) -> [u64; 4] {
        // SAFETY: as in `expand`.
        unsafe { compact_bmi2(&self.masks, code) }
    }

    /// Expand a batch of channel values (the hot loop stays inside the BMI2 function).
    pub fn expand_slice(&self, q: &[[u64; 4]], out: &mut [u64]) {
        // SAFETY: as in `expand`.
        unsafe { expand_slice_bmi2(&self.masks, q, out) }
    }

    /// Split a batch of codes (the hot loop stays inside the BMI2 function).
    pub fn compact_slice(&self, codes: &[u64], out: &mut [[u64; 4]]) {
        // SAFETY: as in `expand`.
        unsafe { compact_slice_bmi2(&self.masks, codes, out) }
    }
}

/// # Safety
/// The CPU must support BMI2.
#[target_feature(enable = "bmi2")]
#[inline]
unsafe fn expand_bmi2(m: &[u64; 4], q: [u64; 4]) -> u64 {
    _pdep_u64(q[0], m[0]) | _pdep_u64(q[1], m[1]) | _pdep_u64(q[2], m[2]) | _pdep_u64(q[3], m[3])
}

/// # Safety
/// The CPU must support BMI2.
#[target_feature(enable = "bmi2")]
#[inline]
unsafe fn compact_bmi2(m: &[u64; 4], code: u64) -> [u64; 4] {
    [
        _pext_u64(code, m[0]),
        _pext_u64(code, m[1]),
        _pext_u64(code, m[2]),
        _pext_u64(code, m[3]),
    ]
}

/// # Safety
/// The CPU must support BMI2.
#[target_feature(enable = "bmi2")]
unsafe fn expand_slice_bmi2(m: &[u64; 4], q: &[[u64; 4]], out: &mut [u64]) {
    for (o, v) in out.iter_mut().zip(q) {
        *o = _pdep_u64(v[0], m[0])
            | _pdep_u64(v[1], m[1])
            | _pdep_u64(v[2], m[2])
            | _pdep_u64(v[3], m[3]);
    }
}

/// # Safety
/// The CPU must support BMI2.
#[target_feature(enable = "bmi2")]
unsafe fn compact_slice_bmi2(m: &[u64; 4], codes: &[u64], out: &mut [[u64; 4]]) {
    for (o, &c) in out.iter_mut().zip(codes) {
        *o = [
            _pext_u64(c, m[0]),
            _pext_u64(c, m[1]),
            _pext_u64(c, m[2]),
            _pext_u64(c, m[3]),
        ];
    }
}
