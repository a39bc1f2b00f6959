//! Parallel batch encoding: splits a slice of primitive boxes into chunks that rayon encodes
//! with the encoder's dispatched pipeline. Codes depend only on each box and the encoder, so
//! the result is bit-identical to one thread (and to `Encoder::encode` on each box). Also the
//! measurement kernels shared by `emc layout` and the benches (encode-only loop, streaming
//! baseline, thread CPU clock).
#![forbid(unsafe_code)]

use emc_core::{Aabb, Encoder, Error, Expander};
use rayon::prelude::*;

/// Boxes per parallel task: large enough that task overhead vanishes (≈ 0.1–0.3 ms of work),
/// small enough to balance two to dozens of threads; a multiple of four (the SIMD group).
pub const CHUNK: usize = 1 << 15;

/// Encode `boxes` into `out` (same length) on the current rayon pool.
pub fn encode_parallel(enc: &Encoder, boxes: &[Aabb], out: &mut [u64]) -> Result<(), Error> {
    if boxes.len() != out.len() {
        return Err(Error::LengthMismatch(boxes.len(), out.len()));
    }
    out.par_chunks_mut(CHUNK)
        .zip(boxes.par_chunks(CHUNK))
        .try_for_each(|(o, b)| enc.encode_batch(b, o))
}

/// Encode `boxes` into `u32` codes on the current rayon pool; an error when the layout is wider
/// than 32 bits or the lengths differ.
pub fn encode_parallel_u32(enc: &Encoder, boxes: &[Aabb], out: &mut [u32]) -> Result<(), Error> {
    if !enc.layout().fits_u32() {
        return Err(Error::CodeTooWide(enc.layout().len()));
    }
    if boxes.len() != out.len() {
        return Err(Error::LengthMismatch(boxes.len(), out.len()));
    }
    out.par_chunks_mut(CHUNK)
        .zip(boxes.par_chunks(CHUNK))
        .try_for_each(|(o, b)| enc.encode_batch_u32(b, o))
}

/// Expand pre-quantised channel values with one backend, in a loop monomorphic in the backend
/// (the "encode-only" kernel of the benchmarks).
pub fn expand_slice(exp: &Expander, q: &[[u64; 4]], out: &mut [u64]) -> Result<(), Error> {
    if q.len() != out.len() {
        return Err(Error::LengthMismatch(q.len(), out.len()));
    }
    exp.expand_slice(q, out);
    Ok(())
}

/// The streaming baseline of the pipeline: reads every byte of every box (24 B) and writes one
/// `u64` (8 B) per box, with one xor per word: the memory ceiling an encoder is compared to.
/// Never inlined, so that profilers (callgrind `--toggle-collect`) find it by name.
#[inline(never)]
pub fn stream_baseline(boxes: &[Aabb], out: &mut [u64]) -> Result<(), Error> {
    if boxes.len() != out.len() {
        return Err(Error::LengthMismatch(boxes.len(), out.len()));
    }
    for (o, b) in out.iter_mut().zip(boxes) {
        let lo = b.min.x.to_bits() ^ b.min.y.to_bits() ^ b.min.z.to_bits();
        let hi = b.max.x.to_bits() ^ b.max.y.to_bits() ^ b.max.z.to_bits();
        *o = (hi as u64) << 32 | lo as u64;
    }
    Ok(())
}
