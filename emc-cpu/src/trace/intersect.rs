//! Robust ray geometry of the tracer: the ray with its precomputed constants, the watertight
//! ray–triangle test of Woop, Benthin and Wald (2013) and the conservative slab test of Ize
//! (2013). Every traversal path (scalar or SIMD) calls these or agrees with them bit for bit.
#![forbid(unsafe_code)]

use glam::Vec3;

/// A ray: origin, direction (need not be normalized, must be finite and non-zero), the
/// closed parameter interval `[tnear, tfar]` in which hits count, and a mask: a geometry of a
/// [`crate::trace::Scene`] is seen only when its mask and the ray's share a bit (an
/// [`crate::trace::Accel`] ignores the mask).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Origin.
    pub origin: Vec3,
    /// Direction.
    pub dir: Vec3,
    /// Smallest accepted hit distance (in units of `dir`).
    pub tnear: f32,
    /// Largest accepted hit distance; `f32::INFINITY` for an unbounded ray.
    pub tfar: f32,
    /// Geometry mask ([`Ray::ALL`] by default: every geometry is seen).
    pub mask: u32,
}

impl Ray {
    /// The mask that sees every geometry.
    pub const ALL: u32 = u32::MAX;

    /// A ray over `[0, +inf]` that sees every geometry.
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Ray {
        Ray {
            origin,
            dir,
            tnear: 0.0,
            tfar: f32::INFINITY,
            mask: Ray::ALL,
        }
    }

    /// The same ray with mask `mask`.
    #[inline]
    pub fn with_mask(self, mask: u32) -> Ray {
        Ray { mask, ..self }
    }

    /// A ray over `[tnear, tfar]` that sees every geometry.
    #[inline]
    pub fn segment(origin: Vec3, dir: Vec3, tnear: f32, tfar: f32) -> Ray {
        Ray {
            origin,
            dir,
            tnear,
            tfar,
            mask: Ray::ALL,
        }
    }

    /// True when origin, direction and interval are usable: finite origin and direction, a
    /// non-zero direction, `tnear` finite and `tnear <= tfar` (no NaN).
    #[inline]
    pub fn is_valid(&self) -> bool {
        // Without branches (a two-level trace checks every ray it sends into an instance):
        // x · 0 is ±0 for a finite x and NaN otherwise, so the sum is 0 exactly when origin,
        // direction and `tnear` are all finite.
        let (o, d) = (self.origin, self.dir);
        let finite = (o * 0.0 + d * 0.0).element_sum() + self.tnear * 0.0 == 0.0;
        let nonzero = (d.x != 0.0) | (d.y != 0.0) | (d.z != 0.0);
        finite & nonzero & (self.tnear <= self.tfar)
    }
}

/// The closest hit of a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Hit distance along the ray (in units of `dir`).
    pub t: f32,
    /// Primitive id: the triangle's index in its mesh, or the custom primitive's index.
    pub prim: u32,
    /// Barycentric weight of vertex 1 (for a custom primitive, what its callback returned).
    pub u: f32,
    /// Barycentric weight of vertex 2 (likewise).
    pub v: f32,
    /// Geometry id in the scene that holds the primitive (0 for an [`crate::trace::Accel`]).
    pub geom: u32,
    /// Id of the instance (a geometry of the top-level scene) the hit was found through, or
    /// [`Hit::NO_INSTANCE`].
    pub instance: u32,
}

impl Hit {
    /// [`Hit::instance`] of a hit found without an instance.
    pub const NO_INSTANCE: u32 = u32::MAX;

    /// A hit of triangle (or primitive) `prim` of geometry 0, not through an instance.
    #[inline(always)]
    pub fn triangle(t: f32, prim: u32, u: f32, v: f32) -> Hit {
        Hit {
            t,
            prim,
            u,
            v,
            geom: 0,
            instance: Hit::NO_INSTANCE,
        }
    }
}

/// `γ(3) = 3u / (1 − 3u)` with `u = 2^-24`, the error bound of three rounded operations.
const GAMMA3: f32 = 3.0 * (f32::EPSILON * 0.5) / (1.0 - 3.0 * (f32::EPSILON * 0.5));

/// Ize's widening factor for the far slab distance, `1 + 2γ(3)`, rounded up.
pub const FAR_WIDEN: f32 = 1.0 + 2.0 * GAMMA3;

/// The per-ray constants of both tests, computed once per ray ([`PreRay::new`]; the 8-wide
/// SIMD kernels make the box constants first and the triangle test's only once the ray
/// enters a child of the root).
///
/// Box test: `inv = 1/dir` (±inf for a ±0 component) and, per axis, which box plane is near
/// (`near_is_max[a]`, taken from the sign bit of `dir[a]`, so `-0.0` counts as negative).
/// Triangle test: the axis permutation `kx, ky, kz` (`kz` = largest |dir| component, `kx, ky`
/// swapped when `dir[kz] < 0` to keep the winding) and the shear `sx, sy, sz`.
#[derive(Clone, Copy, Debug)]
pub struct PreRay {
    /// Origin, as an array.
    pub org: [f32; 3],
    /// Direction, as an array.
    pub dir: [f32; 3],
    /// Component-wise reciprocal of the direction.
    pub inv: [f32; 3],
    /// `inv` times [`FAR_WIDEN`]: the far slab distance's factor (see [`slab_test`]).
    pub inv_far: [f32; 3],
    /// Per axis: the near plane is the box's max (direction sign bit set).
    pub near_is_max: [bool; 3],
    /// Permuted axes of the watertight test.
    pub k: [usize; 3],
    /// Shear constants `(dir[kx]/dir[kz], dir[ky]/dir[kz], 1/dir[kz])`.
    pub shear: [f32; 3],
    /// The closed interval of accepted hits.
    pub tnear: f32,
    /// Upper end of the interval (shrinks as closer hits are found).
    pub tfar: f32,
}

impl PreRay {
    /// Precompute the constants of `ray` (which must satisfy [`Ray::is_valid`]).
    #[inline]
    pub fn new(ray: &Ray) -> PreRay {
        let mut r = PreRay::boxes(ray);
        r.add_triangle_constants();
        r
    }

    /// The box test's constants of `ray` alone (`ray` must satisfy [`Ray::is_valid`]): the
    /// triangle test's `k` and `shear` are left unset (`shear` NaN) until
    /// [`PreRay::add_triangle_constants`], which makes them exactly as [`PreRay::new`] does.
    /// For the kernels that make them only once the ray enters a child of the root: most
    /// primary rays of an object seen from outside enter none.
    #[inline(always)]
    pub(crate) fn boxes(ray: &Ray) -> PreRay {
        let org = ray.origin.to_array();
        let dir = ray.dir.to_array();
        // Divisions four at a time (one `divps` where a scalar `divss` each cost a per-ray
        // constant of about a dozen cycles): IEEE division rounds the same in either form.
        let inv4 = glam::Vec4::ONE / glam::Vec4::new(dir[0], dir[1], dir[2], 1.0);
        let inv = [inv4.x, inv4.y, inv4.z];
        let near_is_max = [
            dir[0].is_sign_negative(),
            dir[1].is_sign_negative(),
            dir[2].is_sign_negative(),
        ];
        PreRay {
            org,
            dir,
            inv,
            inv_far: inv.map(|i| i * FAR_WIDEN),
            near_is_max,
            k: [0, 1, 2],
            shear: [f32::NAN; 3],
            tnear: ray.tnear,
            tfar: ray.tfar,
        }
    }

    /// Make the triangle test's constants (see [`PreRay::boxes`]).
    #[inline(always)]
    pub(crate) fn add_triangle_constants(&mut self) {
        let dir = self.dir;
        let a = [dir[0].abs(), dir[1].abs(), dir[2].abs()];
        // Largest component; ties go to the lower axis (deterministic).
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if dir[kz] < 0.0 {
            core::mem::swap(&mut kx, &mut ky);
        }
        let s4 = glam::Vec4::new(dir[kx], dir[ky], 1.0, 1.0) / glam::Vec4::splat(dir[kz]);
        self.k = [kx, ky, kz];
        self.shear = [s4.x, s4.y, s4.z];
    }
}

/// `max` with SSE semantics: `a > b ? a : b` (a NaN in either operand yields `b`).
#[inline(always)]
pub fn max_sse(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// `min` with SSE semantics: `a < b ? a : b` (a NaN in either operand yields `b`).
#[inline(always)]
pub fn min_sse(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// Conservative slab test of one box (the scalar reference of the SIMD node tests).
///
/// Returns the entry distance when the ray's interval `[tnear, tfar]` meets the box. The far
/// distance of each slab is widened by [`FAR_WIDEN`] (Ize 2013), so rounding never culls a box
/// the exact ray touches: it is `(fp − o) · inv_far` with `inv_far = inv · FAR_WIDEN` rounded
/// once per ray, three roundings on the way from `(fp − o) · inv` as in Ize's
/// `((fp − o) · inv) · FAR_WIDEN`, so the same factor covers them, with one multiplication
/// less per box. A zero direction component gives `inv = ±inf`; a slab distance is
/// then `±inf` (origin inside/outside the slab) or NaN (origin exactly on the plane), and the
/// NaN is discarded by the operand order of [`max_sse`]/[`min_sse`], which keeps the interval
/// unchanged: no NaN ever escapes. An empty box (min = +inf, max = −inf) never passes.
#[inline(always)]
pub fn slab_test(r: &PreRay, min: [f32; 3], max: [f32; 3], tfar: f32) -> Option<f32> {
    let mut t0 = r.tnear;
    let mut t1 = tfar;
    for a in 0..3 {
        let (np, fp) = if r.near_is_max[a] {
            (max[a], min[a])
        } else {
            (min[a], max[a])
        };
        let tn = (np - r.org[a]) * r.inv[a];
        let tf = (fp - r.org[a]) * r.inv_far[a];
        t0 = max_sse(tn, t0);
        t1 = min_sse(tf, t1);
    }
    (t0 <= t1).then_some(t0)
}

/// The edge function `a_x·b_y − a_y·b_x` in `f64`, used when the `f32` value is exactly 0
/// (Woop et al.'s fallback that keeps shared edges consistent).
#[inline(never)]
#[cold]
fn edge_f64(ax: f32, ay: f32, bx: f32, by: f32) -> f32 {
    (ax as f64 * by as f64 - ay as f64 * bx as f64) as f32
}

/// Watertight ray–triangle test (Woop, Benthin, Wald 2013), two-sided.
///
/// Returns `(t, u, v)` for a hit with `r.tnear <= t <= tmax`. Rays through a shared edge or
/// vertex hit at least one of the triangles sharing it (the edge functions of the two sides
/// are exact negations, and zero values are recomputed in `f64`). Degenerate (zero-area)
/// triangles and rays in the triangle's plane never hit.
#[inline(always)]
pub fn triangle_test(r: &PreRay, v: &[[f32; 3]; 3], tmax: f32) -> Option<(f32, f32, f32)> {
    debug_assert!(
        !r.shear[2].is_nan(),
        "triangle test of a ray without its constants"
    );
    let [kx, ky, kz] = r.k;
    let [sx, sy, sz] = r.shear;
    let rel = |p: &[f32; 3]| [p[0] - r.org[0], p[1] - r.org[1], p[2] - r.org[2]];
    let a = rel(&v[0]);
    let b = rel(&v[1]);
    let c = rel(&v[2]);
    let ax = a[kx] - sx * a[kz];
    let ay = a[ky] - sy * a[kz];
    let bx = b[kx] - sx * b[kz];
    let by = b[ky] - sy * b[kz];
    let cx = c[kx] - sx * c[kz];
    let cy = c[ky] - sy * c[kz];
    let mut u = cx * by - cy * bx;
    let mut w_ = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || w_ == 0.0 || w == 0.0 {
        u = edge_f64(cx, cy, bx, by);
        w_ = edge_f64(ax, ay, cx, cy);
        w = edge_f64(bx, by, ax, ay);
    }
    let vv = w_;
    if (u < 0.0 || vv < 0.0 || w < 0.0) && (u > 0.0 || vv > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + vv + w;
    if det == 0.0 {
        return None;
    }
    let az = sz * a[kz];
    let bz = sz * b[kz];
    let cz = sz * c[kz];
    let tt = u * az + vv * bz + w * cz;
    let t = tt / det;
    // NaN-safe: a NaN `t` fails both comparisons.
    if t >= r.tnear && t <= tmax {
        let inv_det = 1.0 / det;
        Some((t, vv * inv_det, w * inv_det))
    } else {
        None
    }
}

/// True when a candidate `(t, prim)` beats the best so far: smaller `t`, or equal `t` and a
/// lower triangle id (the tie rule every path shares).
#[inline(always)]
pub fn better(t: f32, prim: u32, best_t: f32, best_prim: u32) -> bool {
    t < best_t || (t == best_t && prim < best_prim)
}

/// Closest hit over all triangles by brute force (the reference every BVH path must equal).
pub fn brute_force_closest(ray: &Ray, tris: &[[Vec3; 3]]) -> Option<Hit> {
    if !ray.is_valid() {
        return None;
    }
    let r = PreRay::new(ray);
    let mut best: Option<Hit> = None;
    for (i, tri) in tris.iter().enumerate() {
        let v = [tri[0].to_array(), tri[1].to_array(), tri[2].to_array()];
        let tmax = best.map_or(r.tfar, |h| h.t);
        if let Some((t, u, w)) = triangle_test(&r, &v, tmax) {
            let prim = i as u32;
            if best.is_none_or(|h| better(t, prim, h.t, h.prim)) {
                best = Some(Hit::triangle(t, prim, u, w));
            }
        }
    }
    best
}

/// Any hit over all triangles by brute force.
pub fn brute_force_occluded(ray: &Ray, tris: &[[Vec3; 3]]) -> bool {
    if !ray.is_valid() {
        return false;
    }
    let r = PreRay::new(ray);
    tris.iter().any(|tri| {
        let v = [tri[0].to_array(), tri[1].to_array(), tri[2].to_array()];
        triangle_test(&r, &v, r.tfar).is_some()
    })
}
