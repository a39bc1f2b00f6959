//! The benchmark workloads of the tracer, exactly as the shared benchmark protocol defines
//! them: the camera ("outside" or "center"), primary rays in 8×8 tiles, ambient-occlusion rays
//! from `pcg_hash`, plus diffuse bounce rays; traced in parallel over tiles, deterministic.
#![forbid(unsafe_code)]

use glam::Vec3;
use rayon::prelude::*;

use crate::trace::intersect::{Hit, Ray};
use crate::trace::traverse::{closest, occluded, NodeTest, TraceStats};
use crate::trace::wide::WideBvh;

/// Tile edge in pixels.
pub const TILE: u32 = 8;

/// Where the protocol camera stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraMode {
    /// Outside the scene, looking at the centre from `c + 0.9·diag·normalize(0.55, 0.6, 1)`.
    Outside,
    /// At the centre, looking along `normalize(1, −0.2, 0.3)` (interior scenes).
    Center,
}

impl CameraMode {
    /// The protocol's choice for a scene name: `Center` for `pbrt-bathroom`, else `Outside`.
    pub fn for_scene(name: &str) -> CameraMode {
        if name.contains("pbrt-bathroom") {
            CameraMode::Center
        } else {
            CameraMode::Outside
        }
    }
}

impl core::str::FromStr for CameraMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "outside" => Ok(CameraMode::Outside),
            "center" | "centre" => Ok(CameraMode::Center),
            _ => Err(format!("unknown camera `{s}` (outside, center)")),
        }
    }
}

/// A 3-vector in `f64` (the camera is computed in double precision).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DVec3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

impl DVec3 {
    /// The vector `(x, y, z)`.
    pub const fn new(x: f64, y: f64, z: f64) -> DVec3 {
        DVec3 { x, y, z }
    }
    /// Widen an `f32` vector.
    pub fn from_f32(v: Vec3) -> DVec3 {
        DVec3::new(v.x as f64, v.y as f64, v.z as f64)
    }
    /// Round to `f32`.
    pub fn as_vec3(self) -> Vec3 {
        Vec3::new(self.x as f32, self.y as f32, self.z as f32)
    }
    /// Dot product.
    pub fn dot(self, o: DVec3) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    /// Cross product.
    pub fn cross(self, o: DVec3) -> DVec3 {
        DVec3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    /// Euclidean length.
    pub fn length(self) -> f64 {
        self.dot(self).sqrt()
    }
    /// This vector divided by its length.
    pub fn normalize(self) -> DVec3 {
        self * (1.0 / self.length())
    }
}

impl core::ops::Add for DVec3 {
    type Output = DVec3;
    fn add(self, o: DVec3) -> DVec3 {
        DVec3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl core::ops::Sub for DVec3 {
    type Output = DVec3;
    fn sub(self, o: DVec3) -> DVec3 {
        DVec3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

impl core::ops::Mul<f64> for DVec3 {
    type Output = DVec3;
    fn mul(self, k: f64) -> DVec3 {
        DVec3::new(self.x * k, self.y * k, self.z * k)
    }
}

impl core::ops::Mul<DVec3> for f64 {
    type Output = DVec3;
    fn mul(self, v: DVec3) -> DVec3 {
        v * self
    }
}

/// The protocol's scene measures: bounds of the referenced vertices, centre and diagonal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneFrame {
    /// Minimum corner of the referenced vertices.
    pub min: Vec3,
    /// Maximum corner.
    pub max: Vec3,
    /// Centre `(min + max) / 2`, in `f64`.
    pub center: DVec3,
    /// Length of the diagonal, in `f64`.
    pub diag: f64,
}

impl SceneFrame {
    /// Measures of the triangles `tris`.
    pub fn of(tris: &[[Vec3; 3]]) -> SceneFrame {
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for t in tris {
            for v in t {
                min = min.min(*v);
                max = max.max(*v);
            }
        }
        SceneFrame::of_box(min, max)
    }

    /// Measures of the box `[min, max]`.
    pub fn of_box(min: Vec3, max: Vec3) -> SceneFrame {
        let (lo, hi) = (DVec3::from_f32(min), DVec3::from_f32(max));
        SceneFrame {
            min,
            max,
            center: (lo + hi) * 0.5,
            diag: (hi - lo).length(),
        }
    }
}

/// A pinhole camera: eye, forward, right and up vectors (`f64`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position.
    pub eye: DVec3,
    /// Unit forward direction.
    pub fwd: DVec3,
    /// Unit right direction.
    pub right: DVec3,
    /// Camera up direction.
    pub up: DVec3,
    /// `tan(fov_y / 2)`.
    pub tan_half: f64,
}

impl Camera {
    /// The protocol camera for `frame` (vertical FOV 60°).
    pub fn protocol(frame: &SceneFrame, mode: CameraMode) -> Camera {
        let c = frame.center;
        let (eye, fwd) = match mode {
            CameraMode::Outside => {
                let eye = c + 0.9 * frame.diag * DVec3::new(0.55, 0.6, 1.0).normalize();
                (eye, (c - eye).normalize())
            }
            CameraMode::Center => (c, DVec3::new(1.0, -0.2, 0.3).normalize()),
        };
        let right = fwd.cross(DVec3::new(0.0, 1.0, 0.0)).normalize();
        let up = right.cross(fwd);
        Camera {
            eye,
            fwd,
            right,
            up,
            tan_half: (30.0f64).to_radians().tan(),
        }
    }

    /// The ray through the centre of pixel `(px, py)` of a `w × h` image.
    pub fn ray(&self, px: u32, py: u32, w: u32, h: u32) -> Ray {
        let sx = (2.0 * (px as f64 + 0.5) / w as f64 - 1.0) * self.tan_half;
        let sy = (1.0 - 2.0 * (py as f64 + 0.5) / h as f64) * self.tan_half;
        let d = (self.fwd + sx * self.right + sy * self.up).normalize();
        Ray::new(self.eye.as_vec3(), d.as_vec3())
    }
}

/// Pixel of the `i`-th ray in tile order (8×8 tiles row-major, pixels row-major inside a
/// tile; edge tiles are clipped to the image).
pub fn tile_order(w: u32, h: u32) -> Vec<(u32, u32)> {
    let mut out = Vec::with_capacity(w as usize * h as usize);
    for ty in (0..h).step_by(TILE as usize) {
        for tx in (0..w).step_by(TILE as usize) {
            for py in ty..(ty + TILE).min(h) {
                for px in tx..(tx + TILE).min(w) {
                    out.push((px, py));
                }
            }
        }
    }
    out
}

/// Primary rays of a `w × h` image in tile order.
pub fn primary_rays(cam: &Camera, w: u32, h: u32) -> Vec<Ray> {
    let px = tile_order(w, h);
    px.par_iter().map(|&(x, y)| cam.ray(x, y, w, h)).collect()
}

/// The protocol's hash (PCG output permutation; wrapping `u32` arithmetic).
#[inline]
pub fn pcg_hash(v: u32) -> u32 {
    let s = v.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let w = ((s >> ((s >> 28) + 4)) ^ s).wrapping_mul(277_803_737);
    (w >> 22) ^ w
}

/// A unit float in `[0, 1)` from the top 24 bits of a hash.
#[inline]
fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Unit geometric normal of a triangle, `normalize(cross(v1 − v0, v2 − v0))`, flipped to face
/// against `dir`.
#[inline]
pub fn facing_normal(t: &[Vec3; 3], dir: Vec3) -> Vec3 {
    let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
    if n.dot(dir) > 0.0 {
        -n
    } else {
        n
    }
}

/// A cosine-weighted direction around unit `n` from two unit floats, through the
/// orthonormal basis of Duff et al. (2017); normalized.
///
/// The basis' branch is taken on `n.z >= 0.0`, so a normal with `n.z == -0.0` uses the same
/// basis as one with `+0.0`. This is the protocol's basis as the peers' counts pin it down:
/// taking the sign bit instead (`copysign(1, n.z)`) flips the basis of every hit whose normal
/// has a negative-zero z, which is common on axis-aligned walls (a facing flip of `+0.0` gives
/// `-0.0`), and moves AO-occluded counts by up to 0.07% (sionna-san-francisco 439,978 against
/// 439,682 with this rule; Embree's harness counts 439,685).
#[inline]
pub fn cosine_dir(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let r = u1.sqrt();
    let phi = 2.0 * core::f32::consts::PI * u2;
    let (x, y, z) = (r * phi.cos(), r * phi.sin(), (1.0 - u1).sqrt());
    let sign = if n.z >= 0.0 { 1.0f32 } else { -1.0 };
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    let b1 = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
    let b2 = Vec3::new(b, sign + n.y * n.y * a, -n.y);
    (b1 * x + b2 * y + n * z).normalize()
}

/// Origin of the secondary rays of a hit: `P = o + t·d`, pushed off by `1e-4·diag` along the
/// facing normal; returns the origin and the normal.
#[inline]
pub fn hit_frame(ray: &Ray, hit: &Hit, tris: &[[Vec3; 3]], diag: f64) -> (Vec3, Vec3) {
    let p = ray.origin + hit.t * ray.dir;
    let n = facing_normal(&tris[hit.prim as usize], ray.dir);
    (p + n * (1e-4 * diag) as f32, n)
}

/// The protocol's 4 AO rays of primary ray `i` (tile-order index) that hit `hit`.
pub fn ao_rays(i: u32, ray: &Ray, hit: &Hit, tris: &[[Vec3; 3]], diag: f64) -> [Ray; 4] {
    let (o, n) = hit_frame(ray, hit, tris, diag);
    let tfar = (0.1 * diag) as f32;
    core::array::from_fn(|k| {
        let h1 = pcg_hash(i.wrapping_mul(4).wrapping_add(k as u32));
        let h2 = pcg_hash(h1);
        Ray::segment(o, cosine_dir(n, unit(h1), unit(h2)), 0.0, tfar)
    })
}

/// One diffuse bounce ray of primary ray `i`: cosine-weighted, unbounded, closest hit. Its
/// hashes are seeded apart from the AO rays' (`i·4 + k` never equals `!i`-based seeds below).
pub fn bounce_ray(i: u32, ray: &Ray, hit: &Hit, tris: &[[Vec3; 3]], diag: f64) -> Ray {
    let (o, n) = hit_frame(ray, hit, tris, diag);
    let h1 = pcg_hash(!i);
    let h2 = pcg_hash(h1 ^ 0x9e37_79b9);
    Ray::new(o, cosine_dir(n, unit(h1), unit(h2)))
}

/// Closest hits of `rays`, in parallel over 64-ray chunks (one tile each), with counters.
pub fn trace_closest(
    bvh: &WideBvh,
    rays: &[Ray],
    kind: NodeTest,
    count: bool,
) -> (Vec<Option<Hit>>, TraceStats) {
    trace_par(rays, None, |ray, s| {
        if count {
            closest::<true>(bvh, ray, kind, s)
        } else {
            closest::<false>(bvh, ray, kind, s)
        }
    })
}

/// Occlusion of `rays`, in parallel over 64-ray chunks, with counters.
pub fn trace_occluded(
    bvh: &WideBvh,
    rays: &[Ray],
    kind: NodeTest,
    count: bool,
) -> (Vec<bool>, TraceStats) {
    trace_par(rays, false, |ray, s| {
        if count {
            occluded::<true>(bvh, ray, kind, s)
        } else {
            occluded::<false>(bvh, ray, kind, s)
        }
    })
}

/// Trace `rays` in parallel over 64-ray chunks with `one`, summing the counters.
fn trace_par<T: Clone + Send + Sync>(
    rays: &[Ray],
    empty: T,
    one: impl Fn(&Ray, &mut TraceStats) -> T + Sync,
) -> (Vec<T>, TraceStats) {
    let mut out = vec![empty; rays.len()];
    let stats = out
        .par_chunks_mut(64)
        .zip(rays.par_chunks(64))
        .map(|(o, r)| {
            let mut s = TraceStats::default();
            for (h, ray) in o.iter_mut().zip(r) {
                *h = one(ray, &mut s);
            }
            s
        })
        .reduce(TraceStats::default, |a, b| a.add(&b));
    (out, stats)
}

/// AO rays of all primary hits, in primary-ray order (4 per hit), with the primary index of
/// each group.
pub fn all_ao_rays(
    primary: &[Ray],
    hits: &[Option<Hit>],
    tris: &[[Vec3; 3]],
    diag: f64,
) -> (Vec<Ray>, Vec<u32>) {
    let owners: Vec<u32> = (0..primary.len() as u32)
        .filter(|&i| hits[i as usize].is_some())
        .collect();
    let rays = owners
        .par_iter()
        .flat_map_iter(|&i| {
            let h = hits[i as usize].as_ref().map(|h| (i, h));
            h.into_iter()
                .flat_map(|(i, h)| ao_rays(i, &primary[i as usize], h, tris, diag))
        })
        .collect();
    (rays, owners)
}

/// Bounce rays of all primary hits, in primary-ray order (1 per hit).
pub fn all_bounce_rays(
    primary: &[Ray],
    hits: &[Option<Hit>],
    tris: &[[Vec3; 3]],
    diag: f64,
) -> Vec<Ray> {
    (0..primary.len())
        .into_par_iter()
        .filter_map(|i| {
            hits[i]
                .as_ref()
                .map(|h| bounce_ray(i as u32, &primary[i], h, tris, diag))
        })
        .collect()
}

/// The protocol counts of one benchmark run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AoCounts {
    /// Primary rays that hit.
    pub primary_hits: u64,
    /// AO rays cast (4 per primary hit).
    pub ao_rays: u64,
    /// AO rays that hit something within `0.1·diag`.
    pub ao_occluded: u64,
}

/// Run the whole protocol (primary rays, then AO rays) at `res × res` and return its counts.
pub fn protocol_counts(bvh: &WideBvh, tris: &[[Vec3; 3]], mode: CameraMode, res: u32) -> AoCounts {
    let frame = SceneFrame::of(tris);
    let cam = Camera::protocol(&frame, mode);
    let primary = primary_rays(&cam, res, res);
    let (hits, _) = trace_closest(bvh, &primary, NodeTest::fastest(), false);
    let (ao, _) = all_ao_rays(&primary, &hits, tris, frame.diag);
    let (occ, _) = trace_occluded(bvh, &ao, NodeTest::fastest(), false);
    AoCounts {
        primary_hits: hits.iter().filter(|h| h.is_some()).count() as u64,
        ao_rays: ao.len() as u64,
        ao_occluded: occ.iter().filter(|&&o| o).count() as u64,
    }
}

/// `n` placements of a mesh whose box is `[lo, hi]` for an instanced benchmark scene: a cube of
/// `⌈∛n⌉³` cells (each 1.25 times the mesh's largest extent) filled in order, each instance
/// rotated about a random axis, scaled by 0.5 to 0.9 (every fourth mirrored in x, every third
/// stretched 1.3 times in y), centred in its cell and jittered by up to a tenth of it.
/// Deterministic in `seed`.
pub fn instance_grid(n: usize, lo: Vec3, hi: Vec3, seed: u64) -> Vec<glam::Affine3A> {
    use glam::{Affine3A, Quat};
    let side = (1..).find(|s: &usize| s.pow(3) >= n).unwrap_or(1);
    let cell = 1.25 * (hi - lo).max_element().max(f32::MIN_POSITIVE);
    let centre = 0.5 * (lo + hi);
    let mut rng = crate::scene::builtin::Pcg32::new(seed, 17);
    (0..n)
        .map(|k| {
            let (i, j, l) = (k % side, (k / side) % side, k / (side * side));
            let jitter = Vec3::new(
                rng.range(-0.1, 0.1),
                rng.range(-0.1, 0.1),
                rng.range(-0.1, 0.1),
            );
            let at = (Vec3::new(i as f32, j as f32, l as f32) + 0.5 + jitter) * cell;
            let axis = Vec3::new(
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            )
            .try_normalize()
            .unwrap_or(Vec3::Z);
            let q = Quat::from_axis_angle(axis, rng.range(0.0, core::f32::consts::TAU));
            let s = rng.range(0.5, 0.9);
            let mut scale = Vec3::splat(s);
            if k % 4 == 3 {
                scale.x = -scale.x;
            }
            if k % 3 == 2 {
                scale.y *= 1.3;
            }
            let m = Affine3A::from_scale_rotation_translation(scale, q, Vec3::ZERO);
            Affine3A::from_translation(at - m.transform_point3(centre)) * m
        })
        .collect()
}
