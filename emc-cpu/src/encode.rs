//! Parallel batch encoding: splits a slice of primitive boxes into chunks that rayon encodes
//! with the encoder's dispatched pipeline. Codes depend only on each box and the encoder, so
//! the result is bit-identical to one thread (and to `Encoder::encode` on each box).

use emc_core::{Aabb, Encoder, Error};
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
