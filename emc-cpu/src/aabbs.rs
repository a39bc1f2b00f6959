//! Pipeline step 1: one box per triangle, from an indexed mesh, in parallel (rayon) on the
//! fastest path of this CPU (AVX2 when present, chosen once at run time) or the scalar path.
//! All paths compute the same min/max and agree bit for bit (tested on every built-in scene).

use std::sync::OnceLock;

use emc_core::{Aabb, SceneBounds};
use glam::Vec3;
use rayon::prelude::*;

/// Triangles per rayon task.
const CHUNK: usize = 1 << 14;

/// An implementation of [`triangle_aabbs`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AabbPath {
    /// Plain Rust, one coordinate at a time (the reference).
    Scalar,
    /// AVX2: one 128-bit unaligned load per vertex (x, y, z and one spare lane), `vminps` /
    /// `vmaxps`, two overlapping 16-byte stores per box.
    Avx2,
}

impl AabbPath {
    /// The best path this CPU supports (detected once).
    pub fn detect() -> AabbPath {
        static PATH: OnceLock<AabbPath> = OnceLock::new();
        *PATH.get_or_init(|| {
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") {
                return AabbPath::Avx2;
            }
            AabbPath::Scalar
        })
    }

    /// True when this CPU can run the path.
    pub fn available(self) -> bool {
        match self {
            AabbPath::Scalar => true,
            AabbPath::Avx2 => AabbPath::detect() == AabbPath::Avx2,
        }
    }

    /// One line saying what the path does and why it was chosen.
    pub fn describe(self) -> &'static str {
        match self {
            AabbPath::Scalar => "scalar (no AVX2 on this CPU, or forced)",
            AabbPath::Avx2 => "avx2 (runtime-detected; 128-bit vertex loads, vminps/vmaxps)",
        }
    }
}

impl std::fmt::Display for AabbPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            AabbPath::Scalar => "scalar",
            AabbPath::Avx2 => "avx2",
        })
    }
}

/// Boxes of the triangles `indices` over `vertices` into `out`, in parallel, on the path of
/// [`AabbPath::detect`].
///
/// Panics when `out.len() != indices.len()` or an index is out of range (both are bugs of the
/// caller: [`crate::scene::load`] guarantees valid indices).
pub fn triangle_aabbs(vertices: &[Vec3], indices: &[[u32; 3]], out: &mut [Aabb]) {
    triangle_aabbs_with(AabbPath::detect(), vertices, indices, out);
}

/// [`triangle_aabbs`] on a chosen path (a path this CPU lacks falls back to scalar).
pub fn triangle_aabbs_with(
    path: AabbPath,
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    out: &mut [Aabb],
) {
    assert_eq!(out.len(), indices.len(), "one box per triangle");
    out.par_chunks_mut(CHUNK)
        .zip(indices.par_chunks(CHUNK))
        .for_each(|(o, t)| chunk_aabbs(path, vertices, t, o));
}

/// Triangle boxes into `out` (one per triangle) and their [`SceneBounds`] in the same pass, on
/// the current rayon pool. The bounds equal [`crate::build::scene_bounds`] of the boxes; a
/// non-finite vertex is reported as that function reports it (the first such triangle).
pub fn triangle_aabbs_bounds(
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    out: &mut [Aabb],
) -> Result<SceneBounds, emc_core::Error> {
    let path = AabbPath::detect();
    out.par_chunks_mut(CHUNK)
        .zip(indices.par_chunks(CHUNK))
        .enumerate()
        .map(|(c, (o, t))| chunk_aabbs_bounds(path, vertices, t, o, c * CHUNK))
        .try_reduce(|| SceneBounds::EMPTY, |a, b| Ok(a.merge(&b)))
}

/// One chunk of [`triangle_aabbs_bounds`]; `base` is the index of its first triangle.
pub fn chunk_aabbs_bounds(
    path: AabbPath,
    vertices: &[Vec3],
    indices: &[[u32; 3]],
    out: &mut [Aabb],
    base: usize,
) -> Result<SceneBounds, emc_core::Error> {
    assert_eq!(out.len(), indices.len(), "one box per triangle");
    #[cfg(target_arch = "x86_64")]
    if path == AabbPath::Avx2 && path.available() && !indices.is_empty() {
        // SAFETY: AVX2 is present (checked by `available`), and the lengths match.
        if let Some(b) = unsafe { avx2::aabbs_bounds(vertices, indices, out) } {
            return Ok(b);
        }
        // A non-finite coordinate: the reference reduction names the triangle.
        return SceneBounds::of(out, base);
    }
    chunk_aabbs(path, vertices, indices, out);
    SceneBounds::of(out, base)
}

/// One chunk, on the calling thread (also the single-thread entry point of benches).
pub fn chunk_aabbs(path: AabbPath, vertices: &[Vec3], indices: &[[u32; 3]], out: &mut [Aabb]) {
    assert_eq!(out.len(), indices.len(), "one box per triangle");
    match path {
        #[cfg(target_arch = "x86_64")]
        AabbPath::Avx2 if path.available() => {
            // SAFETY: AVX2 is present (checked by `available`), and the lengths match.
            unsafe { avx2::aabbs(vertices, indices, out) }
        }
        _ => scalar_aabbs(vertices, indices, out),
    }
}

/// `a < b ? a : b`, the operand order of `minps` (so NaN and ±0 resolve like the SIMD path).
#[inline(always)]
fn min_ps(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `a > b ? a : b`, the operand order of `maxps`.
#[inline(always)]
fn max_ps(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The box of one triangle as every path computes it: `min(min(a, b), c)` per axis with
/// `minps` semantics, `a < b ? a : b` (equal to [`Aabb::from_triangle`] up to the sign of zero).
#[inline(always)]
pub fn triangle_aabb(a: Vec3, b: Vec3, c: Vec3) -> Aabb {
    Aabb {
        min: Vec3::new(
            min_ps(min_ps(a.x, b.x), c.x),
            min_ps(min_ps(a.y, b.y), c.y),
            min_ps(min_ps(a.z, b.z), c.z),
        ),
        max: Vec3::new(
            max_ps(max_ps(a.x, b.x), c.x),
            max_ps(max_ps(a.y, b.y), c.y),
            max_ps(max_ps(a.z, b.z), c.z),
        ),
    }
}

/// The scalar reference path.
pub fn scalar_aabbs(vertices: &[Vec3], indices: &[[u32; 3]], out: &mut [Aabb]) {
    for (o, &[i, j, k]) in out.iter_mut().zip(indices) {
        *o = triangle_aabb(
            vertices[i as usize],
            vertices[j as usize],
            vertices[k as usize],
        );
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use core::arch::x86_64::*;

    use super::{triangle_aabb, Aabb, SceneBounds, Vec3};

    /// [`aabbs`] that also gathers the chunk's [`SceneBounds`] in the same loop: the box union
    /// in `f32` lanes and the centre sums `min + max` in `f64` lanes (exact: the centre is
    /// half of it, and halving commutes with min and max). `None` when some box coordinate is
    /// not finite (`x − x` is NaN exactly then); the caller then asks the reference.
    ///
    /// # Safety
    /// The CPU must support AVX2; `out.len() == indices.len() > 0`.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn aabbs_bounds(
        vertices: &[Vec3],
        indices: &[[u32; 3]],
        out: &mut [Aabb],
    ) -> Option<SceneBounds> {
        // SAFETY: same contract as ours.
        unsafe { aabbs(vertices, indices, out) };
        let n = out.len();
        let p = out.as_ptr() as *const f32;
        // SAFETY: AVX2 is enabled for this function; the loads read box t's six floats and
        // (for t + 1 < n) the next box's first two, inside `out`; the last box is read by a
        // scalar path.
        unsafe {
            let mut lo = _mm_set1_ps(f32::INFINITY);
            let mut hi = _mm_set1_ps(f32::NEG_INFINITY);
            let mut cmin = _mm256_set1_pd(f64::INFINITY);
            let mut cmax = _mm256_set1_pd(f64::NEG_INFINITY);
            let mut bad = _mm_setzero_ps();
            let mut step = |mn: __m128, mx: __m128| {
                lo = _mm_min_ps(lo, mn);
                hi = _mm_max_ps(hi, mx);
                let c = _mm256_add_pd(_mm256_cvtps_pd(mn), _mm256_cvtps_pd(mx));
                cmin = _mm256_min_pd(cmin, c);
                cmax = _mm256_max_pd(cmax, c);
                let z = _mm_add_ps(_mm_sub_ps(mn, mn), _mm_sub_ps(mx, mx));
                bad = _mm_or_ps(bad, _mm_cmpunord_ps(z, z));
            };
            for t in 0..n - 1 {
                step(_mm_loadu_ps(p.add(6 * t)), _mm_loadu_ps(p.add(6 * t + 3)));
            }
            let b = out[n - 1];
            step(
                _mm_setr_ps(b.min.x, b.min.y, b.min.z, 0.0),
                _mm_setr_ps(b.max.x, b.max.y, b.max.z, 0.0),
            );
            // Lane 3 holds the next box's first coordinates (or 0): ignored.
            if _mm_movemask_ps(bad) & 0b111 != 0 {
                return None;
            }
            let (mut l, mut h) = ([0.0f32; 4], [0.0f32; 4]);
            _mm_storeu_ps(l.as_mut_ptr(), lo);
            _mm_storeu_ps(h.as_mut_ptr(), hi);
            let (mut cl, mut ch) = ([0.0f64; 4], [0.0f64; 4]);
            _mm256_storeu_pd(cl.as_mut_ptr(), cmin);
            _mm256_storeu_pd(ch.as_mut_ptr(), cmax);
            Some(SceneBounds {
                centroid_min: [cl[0] * 0.5, cl[1] * 0.5, cl[2] * 0.5],
                centroid_max: [ch[0] * 0.5, ch[1] * 0.5, ch[2] * 0.5],
                prim: Aabb::new(Vec3::new(l[0], l[1], l[2]), Vec3::new(h[0], h[1], h[2])),
                count: n,
            })
        }
    }

    /// AVX2 boxes.
    ///
    /// Each vertex is read with one 16-byte load at its address: lanes `[x y z w]` where `w`
    /// is the next vertex's x (or, for the last vertex, out of bounds: such triangles take the
    /// scalar path). The box is written with two 16-byte stores:
    ///
    /// ```text
    /// bytes   0      4      8      12     16     20     24
    ///         min.x  min.y  min.z  max.x  max.y  max.z  (next box)
    /// store1  [mx    my     mz     junk]
    /// store2                       [Mx    My     Mz     junk]
    /// ```
    /// so store 2 overwrites store 1's junk and its own junk lands on the next box, which is
    /// written afterwards; the last box of the slice is written by the scalar path.
    ///
    /// # Safety
    /// The CPU must support AVX2; `out.len() == indices.len()`.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn aabbs(vertices: &[Vec3], indices: &[[u32; 3]], out: &mut [Aabb]) {
        debug_assert_eq!(out.len(), indices.len());
        let n = indices.len();
        if n == 0 {
            return;
        }
        // Vertices whose 16-byte load stays inside the slice: all but the last.
        let safe = vertices.len().saturating_sub(1) as u32;
        let vp = vertices.as_ptr() as *const f32;
        let op = out.as_mut_ptr() as *mut f32;
        for (t, &[i, j, k]) in indices[..n - 1].iter().enumerate() {
            if i.max(j).max(k) >= safe {
                // Last vertex (16-byte load would overrun) or an invalid index: the scalar
                // path reads safely (and panics on a bad index, like the scalar path).
                let bx = triangle_aabb(
                    vertices[i as usize],
                    vertices[j as usize],
                    vertices[k as usize],
                );
                // SAFETY: t < n = out.len(); written through the same raw pointer as the
                // SIMD stores so that no reborrow of `out` invalidates it.
                unsafe { (op as *mut Aabb).add(t).write(bx) };
                continue;
            }
            // SAFETY: i, j, k < vertices.len() - 1, so each 16-byte load covers vertex i and
            // the first float of vertex i + 1, all inside `vertices` (Vec3 is 3 packed f32).
            // t + 1 < n, so the stores at byte offsets 24t .. 24t + 28 stay inside `out`.
            unsafe {
                let a = _mm_loadu_ps(vp.add(3 * i as usize));
                let b = _mm_loadu_ps(vp.add(3 * j as usize));
                let c = _mm_loadu_ps(vp.add(3 * k as usize));
                let mn = _mm_min_ps(_mm_min_ps(a, b), c);
                let mx = _mm_max_ps(_mm_max_ps(a, b), c);
                _mm_storeu_ps(op.add(6 * t), mn);
                _mm_storeu_ps(op.add(6 * t + 3), mx);
            }
        }
        let [i, j, k] = indices[n - 1];
        let last = triangle_aabb(
            vertices[i as usize],
            vertices[j as usize],
            vertices[k as usize],
        );
        // SAFETY: n - 1 < out.len().
        unsafe { (op as *mut Aabb).add(n - 1).write(last) };
    }
}
