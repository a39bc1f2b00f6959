//! The C ABI of the golden model, for accelerator models outside Rust (C/C++, SystemC, gem5,
//! DPI-C, Python via ctypes/cffi): opaque handles for emc-core's encoder and for the unit,
//! status codes, no panic across the boundary (every entry point runs under `catch_unwind`).
//! The header is `emc-hwsim/include/emc_hwsim.h`; a test keeps it equal to these signatures.
//!
//! This module is the one documented exception to emc-hwsim's `forbid(unsafe_code)`: it reads
//! and writes caller memory through raw pointers. Every `unsafe` block states its contract.
#![allow(unsafe_code)]

use std::ffi::{c_char, CStr};
use std::panic::{catch_unwind, AssertUnwindSafe};

use emc_core::glam::Vec3;
use emc_core::{Aabb, Encoder, Frame, LayoutSpec};

use crate::datapath::{RoutingChoice, Unit, UnitOptions};
use crate::memory::MemoryConfig;

/// Status codes of every entry point (`EmcStatus` in C).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EmcStatus {
    /// Success.
    Ok = 0,
    /// A required pointer was null.
    NullPointer = 1,
    /// The layout name is not valid UTF-8 or not a layout.
    BadLayout = 2,
    /// The scene boxes give no frame (empty, non-finite or inverted boxes).
    BadScene = 3,
    /// The unit cannot be configured so (routing code, routing for the layout, memory knobs).
    BadConfig = 4,
    /// An internal error was caught at the boundary (a bug; nothing was written).
    Panic = 5,
}

/// A box as C lays it out: `min[3]`, `max[3]` (`EmcAabb`).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct EmcAabb {
    /// Minimum corner.
    pub min: [f32; 3],
    /// Maximum corner.
    pub max: [f32; 3],
}

impl From<&EmcAabb> for Aabb {
    fn from(b: &EmcAabb) -> Aabb {
        Aabb::new(Vec3::from(b.min), Vec3::from(b.max))
    }
}

/// emc-core's encoder for one layout and frame (`EmcEncoder`, opaque in C).
#[derive(Debug)]
pub struct EmcEncoder(Encoder);

/// The modelled unit for one layout, frame and options (`EmcUnit`, opaque in C).
#[derive(Debug)]
pub struct EmcUnit(Unit);

/// Run `f` with panics turned into [`EmcStatus::Panic`].
fn guard(f: impl FnOnce() -> EmcStatus) -> EmcStatus {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or(EmcStatus::Panic)
}

/// The layout name and the frame of the scene boxes.
///
/// # Safety
/// `layout` must be a NUL-terminated string and `boxes` point to `n` readable `EmcAabb`
/// (either may be checked null here; `n = 0` allows a dangling `boxes`).
unsafe fn layout_and_frame(
    layout: *const c_char,
    boxes: *const EmcAabb,
    n: usize,
) -> Result<(LayoutSpec, Frame), EmcStatus> {
    if layout.is_null() || (boxes.is_null() && n > 0) {
        return Err(EmcStatus::NullPointer);
    }
    // SAFETY: non-null and NUL-terminated by the caller's contract.
    let name = unsafe { CStr::from_ptr(layout) }
        .to_str()
        .map_err(|_| EmcStatus::BadLayout)?;
    let spec: LayoutSpec = name.parse().map_err(|_| EmcStatus::BadLayout)?;
    let slice = if n == 0 {
        &[][..]
    } else {
        // SAFETY: non-null, `n` readable elements by the caller's contract; EmcAabb is plain
        // old data with no invalid bit patterns.
        unsafe { std::slice::from_raw_parts(boxes, n) }
    };
    let aabbs: Vec<Aabb> = slice.iter().map(Aabb::from).collect();
    let frame = Frame::new(&aabbs).map_err(|_| EmcStatus::BadScene)?;
    Ok((spec, frame))
}

/// Encode `n` boxes of `boxes` into `codes` (both checked non-null unless `n = 0`).
///
/// # Safety
/// `boxes` must point to `n` readable `EmcAabb` and `codes` to `n` writable `u64`.
unsafe fn encode_with(
    boxes: *const EmcAabb,
    n: usize,
    codes: *mut u64,
    f: impl Fn(&Aabb) -> u64,
) -> EmcStatus {
    if n == 0 {
        return EmcStatus::Ok;
    }
    if boxes.is_null() || codes.is_null() {
        return EmcStatus::NullPointer;
    }
    // SAFETY: non-null, `n` readable boxes by the caller's contract.
    let input = unsafe { std::slice::from_raw_parts(boxes, n) };
    // SAFETY: non-null, `n` writable codes by the caller's contract, not aliasing `input`
    // (different element types the caller owns separately).
    let out = unsafe { std::slice::from_raw_parts_mut(codes, n) };
    for (o, b) in out.iter_mut().zip(input) {
        *o = f(&Aabb::from(b));
    }
    EmcStatus::Ok
}

/// Create emc-core's encoder for `layout` in the frame of the `n` scene boxes.
///
/// # Safety
/// `layout` is a NUL-terminated string, `boxes` points to `n` boxes, `out` to a writable
/// pointer; on success `*out` owns an encoder to release with [`emc_encoder_free`].
#[no_mangle]
pub unsafe extern "C" fn emc_encoder_new(
    layout: *const c_char,
    boxes: *const EmcAabb,
    n: usize,
    out: *mut *mut EmcEncoder,
) -> EmcStatus {
    guard(|| {
        if out.is_null() {
            return EmcStatus::NullPointer;
        }
        // SAFETY: forwarded caller contract.
        match unsafe { layout_and_frame(layout, boxes, n) } {
            Ok((spec, frame)) => {
                let e = Box::new(EmcEncoder(Encoder::new(&spec, &frame)));
                // SAFETY: `out` is non-null and writable by the caller's contract.
                unsafe { *out = Box::into_raw(e) };
                EmcStatus::Ok
            }
            Err(s) => s,
        }
    })
}

/// Release an encoder (null is allowed and ignored).
///
/// # Safety
/// `e` is null or a pointer from [`emc_encoder_new`] not yet released.
#[no_mangle]
pub unsafe extern "C" fn emc_encoder_free(e: *mut EmcEncoder) {
    let _ = catch_unwind(AssertUnwindSafe(|| {
        if !e.is_null() {
            // SAFETY: created by Box::into_raw in emc_encoder_new, released once.
            drop(unsafe { Box::from_raw(e) });
        }
    }));
}

/// Encode `n` boxes with emc-core's encoder.
///
/// # Safety
/// `e` is a live encoder, `boxes` points to `n` boxes and `codes` to `n` writable codes.
#[no_mangle]
pub unsafe extern "C" fn emc_encoder_encode(
    e: *const EmcEncoder,
    boxes: *const EmcAabb,
    n: usize,
    codes: *mut u64,
) -> EmcStatus {
    guard(|| {
        // SAFETY: null or a live encoder by the caller's contract.
        let Some(e) = (unsafe { e.as_ref() }) else {
            return EmcStatus::NullPointer;
        };
        // SAFETY: forwarded caller contract.
        unsafe { encode_with(boxes, n, codes, |b| e.0.encode(b)) }
    })
}

/// Create the modelled unit for `layout` in the frame of the `n` scene boxes; `routing` is
/// 0 auto, 1 fixed wiring, 2 Beneš, 3 crossbar.
///
/// # Safety
/// As [`emc_encoder_new`]; release with [`emc_unit_free`].
#[no_mangle]
pub unsafe extern "C" fn emc_unit_new(
    layout: *const c_char,
    boxes: *const EmcAabb,
    n: usize,
    routing: u32,
    out: *mut *mut EmcUnit,
) -> EmcStatus {
    guard(|| {
        if out.is_null() {
            return EmcStatus::NullPointer;
        }
        let routing = match routing {
            0 => RoutingChoice::Auto,
            1 => RoutingChoice::Fixed,
            2 => RoutingChoice::Benes,
            3 => RoutingChoice::Crossbar,
            _ => return EmcStatus::BadConfig,
        };
        // SAFETY: forwarded caller contract.
        let (spec, frame) = match unsafe { layout_and_frame(layout, boxes, n) } {
            Ok(x) => x,
            Err(s) => return s,
        };
        let opts = UnitOptions {
            routing,
            ..UnitOptions::default()
        };
        match Unit::for_spec(&spec, &frame, &opts) {
            Ok(u) => {
                // SAFETY: `out` is non-null and writable by the caller's contract.
                unsafe { *out = Box::into_raw(Box::new(EmcUnit(u))) };
                EmcStatus::Ok
            }
            Err(_) => EmcStatus::BadConfig,
        }
    })
}

/// Release a unit (null is allowed and ignored).
///
/// # Safety
/// `u` is null or a pointer from [`emc_unit_new`] not yet released.
#[no_mangle]
pub unsafe extern "C" fn emc_unit_free(u: *mut EmcUnit) {
    let _ = catch_unwind(AssertUnwindSafe(|| {
        if !u.is_null() {
            // SAFETY: created by Box::into_raw in emc_unit_new, released once.
            drop(unsafe { Box::from_raw(u) });
        }
    }));
}

/// Codes of `n` boxes through the unit's datapath.
///
/// # Safety
/// `u` is a live unit, `boxes` points to `n` boxes and `codes` to `n` writable codes.
#[no_mangle]
pub unsafe extern "C" fn emc_unit_encode(
    u: *const EmcUnit,
    boxes: *const EmcAabb,
    n: usize,
    codes: *mut u64,
) -> EmcStatus {
    guard(|| {
        // SAFETY: null or a live unit by the caller's contract.
        let Some(u) = (unsafe { u.as_ref() }) else {
            return EmcStatus::NullPointer;
        };
        // SAFETY: forwarded caller contract.
        unsafe { encode_with(boxes, n, codes, |b| u.0.code(b)) }
    })
}

/// The unit's pipeline depth (cycles from a box entering to its code leaving) and its lane
/// initiation interval.
///
/// # Safety
/// `u` is a live unit; `depth` and `ii` point to writable `u32`.
#[no_mangle]
pub unsafe extern "C" fn emc_unit_latency(
    u: *const EmcUnit,
    depth: *mut u32,
    ii: *mut u32,
) -> EmcStatus {
    guard(|| {
        // SAFETY: null or a live unit by the caller's contract.
        let Some(u) = (unsafe { u.as_ref() }) else {
            return EmcStatus::NullPointer;
        };
        if depth.is_null() || ii.is_null() {
            return EmcStatus::NullPointer;
        }
        // SAFETY: non-null and writable by the caller's contract.
        unsafe {
            *depth = u.0.depth();
            *ii = u.0.lane_ii();
        }
        EmcStatus::Ok
    })
}

/// Cycles of a run of `n` primitives against a memory of `bandwidth_gbps`, `clock_ghz` and
/// `latency_ns` (the model's fast timing mode).
///
/// # Safety
/// `u` is a live unit; `cycles` points to a writable `u64`.
#[no_mangle]
pub unsafe extern "C" fn emc_unit_cycles(
    u: *const EmcUnit,
    n: u64,
    bandwidth_gbps: f64,
    clock_ghz: f64,
    latency_ns: f64,
    cycles: *mut u64,
) -> EmcStatus {
    guard(|| {
        // SAFETY: null or a live unit by the caller's contract.
        let Some(u) = (unsafe { u.as_ref() }) else {
            return EmcStatus::NullPointer;
        };
        if cycles.is_null() {
            return EmcStatus::NullPointer;
        }
        let mem = MemoryConfig {
            bandwidth_gbps,
            clock_ghz,
            latency_ns,
        };
        match u.0.timing(n, &mem) {
            Ok(s) => {
                // SAFETY: non-null and writable by the caller's contract.
                unsafe { *cycles = s.cycles };
                EmcStatus::Ok
            }
            Err(_) => EmcStatus::BadConfig,
        }
    })
}

/// A static, NUL-terminated description of a status code.
#[no_mangle]
pub extern "C" fn emc_status_str(s: u32) -> *const c_char {
    let m: &'static [u8] = match s {
        0 => b"ok\0",
        1 => b"a required pointer was null\0",
        2 => b"not a layout name\0",
        3 => b"the scene boxes give no frame (empty, non-finite or inverted)\0",
        4 => b"the unit cannot be configured so\0",
        5 => b"internal error caught at the C boundary\0",
        _ => b"unknown status\0",
    };
    m.as_ptr().cast()
}
