//! Built-in procedural scenes (`builtin:NAME`): deterministic from a seed, sized by `prims`.
//! They stand for the layouts that stress LBVH builders (uniform soup, a stadium, a flat city,
//! hair, mixed primitive sizes) plus a watertight icosphere for tracer tests.
#![forbid(unsafe_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use glam::Vec3;

use super::{Mesh, SceneError, SceneOptions};

/// Seed used when none is given.
pub const DEFAULT_SEED: u64 = 0x5EED_E3C0_2017;

/// The names accepted after `builtin:`.
pub const NAMES: [&str; 6] = ["uniform", "stadium", "city", "hair", "mixed", "sphere"];

/// The hard-case catalogue, also `builtin:` scenes (see [`generate`] for each one's shape).
pub const HARD_NAMES: [&str; 14] = [
    "hard-point",
    "hard-plane-x",
    "hard-plane-y",
    "hard-plane-z",
    "hard-far",
    "hard-huge",
    "hard-tiny",
    "hard-subnormal",
    "hard-needles",
    "hard-one-big",
    "hard-same-cell",
    "hard-elongated",
    "hard-nonfinite",
    "hard-duplicates",
];

/// The animated built-in scenes: the same mesh (indices) at every frame, vertices moving with
/// [`SceneOptions::frame`] (see [`wave_vertices`]).
pub const ANIMATED_NAMES: [&str; 1] = ["wave"];

/// Frames per unit of time of the animated scenes.
pub const FRAMES_PER_SECOND: f32 = 24.0;

/// Default triangle count of the hard cases, except `hard-one-big` (10^6 tiny + 1) and
/// `hard-same-cell` (2^21 + 1 in one cell + 2 corners).
pub const HARD_DEFAULT_PRIMS: usize = 100_000;

/// Default triangle count of every generator except `sphere` (which defaults to level 7,
/// 327,680 triangles).
pub const DEFAULT_PRIMS: usize = 500_000;

/// Side of the `city` ground in x (the largest extent); y is two thirds of it.
pub const CITY_LENGTH: f32 = 30_000.0;
/// Height cap of `city` buildings: `CITY_LENGTH / CITY_MAX_HEIGHT` = 150 ≥ 100.
pub const CITY_MAX_HEIGHT: f32 = 200.0;

/// Generate `builtin:NAME`.
///
/// Size semantics of `opts.prims` (`None` = [`DEFAULT_PRIMS`]):
/// - `uniform`, `hair`, `mixed`: exactly `prims` triangles;
/// - `stadium`, `city`: exactly `max(prims, 64)` triangles (each part needs a few);
/// - `sphere`: `20·4^L` triangles for the subdivision level `L` in 0..=10 whose count is
///   nearest to `prims` (ties to the smaller level); the seed is not used.
///
/// The hard cases (exactly `prims` triangles unless noted; the default is
/// [`HARD_DEFAULT_PRIMS`]):
/// - `hard-point`: every vertex at one point (1.5, -2.25, 3);
/// - `hard-plane-x` / `-y` / `-z`: `uniform`'s triangles flattened onto the plane x (y, z) = 5;
/// - `hard-far`: 1 mm triangles around centres in a 100-unit cube 10^7 units from the origin
///   (f32 keeps about 1 unit there: most become zero-area);
/// - `hard-huge`: vertices anywhere in ±f32::MAX/2 (finite, but f32 areas overflow);
/// - `hard-tiny`: coordinates in [1, 16) × the smallest normal f32;
/// - `hard-subnormal`: coordinates below the smallest normal (subnormal extents);
/// - `hard-needles`: a third zero-area (repeated or collinear vertices), two thirds needles
///   (length 1, width 1e-7) in the unit cube;
/// - `hard-one-big`: one triangle covering the whole scene among `prims - 1` tiny ones
///   (default 10^6 + 1);
/// - `hard-same-cell`: `prims - 2` triangles inside one cell of 2^-23 of a unit scene (finer than
///   any 63- or 64-bit code resolves) plus 2 small triangles at the corners that span the scene
///   (default 2^21 + 3);
/// - `hard-elongated`: `uniform` stretched to 10^5 × 1 × 1;
/// - `hard-nonfinite`: a `uniform` mesh in which about 1% of the vertices are NaN or ±inf; like
///   a loaded file, those triangles are dropped and counted in [`Mesh::dropped_nonfinite`]
///   (the count is of the remaining triangles);
/// - `hard-duplicates`: every triangle identical (0,0,0), (1,0,0), (0,1,0).
///
/// The animated scene (same indices at every frame, [`SceneOptions::frame`] picks the
/// vertices):
/// - `wave`: an `n × n` grid sheet over the unit square, `2(n − 1)²` triangles with
///   `n = round(√(prims / 2)) + 1` (at least 2), displaced by a travelling wave and twisted
///   about its x axis by an angle that grows with time and with x (see [`wave_vertices`]);
///   the seed is not used.
///
/// `prims = Some(0)` is an error.
pub fn generate(name: &str, opts: &SceneOptions) -> Result<Mesh, SceneError> {
    if opts.prims == Some(0) {
        return Err(SceneError::ZeroPrims(name.to_string()));
    }
    if let Some(kind) = name.strip_prefix("hard-") {
        return hard(kind, name, opts);
    }
    let n = opts.prims.unwrap_or(DEFAULT_PRIMS);
    // Each scene draws from its own stream so that scenes with one seed are unrelated.
    let stream = |k: u64| Pcg32::new(opts.seed, k);
    let mut soup = Soup::with_capacity(n);
    match name {
        "uniform" => uniform(&mut soup, n, &mut stream(1)),
        "stadium" => stadium(&mut soup, n.max(64), &mut stream(2)),
        "city" => city(&mut soup, n.max(64), &mut stream(3)),
        "hair" => hair(&mut soup, n, &mut stream(4)),
        "mixed" => mixed(&mut soup, n, &mut stream(5)),
        "sphere" => {
            let level = sphere_level(opts.prims);
            return Ok(icosphere(level, 1.0));
        }
        "wave" => {
            let side = wave_side(n);
            return Ok(Mesh {
                name: "builtin:wave".to_string(),
                vertices: wave_vertices(side, opts.frame),
                indices: wave_indices(side),
                dropped_nonfinite: 0,
            });
        }
        _ => return Err(SceneError::UnknownBuiltin(name.to_string())),
    }
    let scene = soup.into_scene(format!("builtin:{name}"));
    if scene.indices.is_empty() {
        return Err(SceneError::NoTriangles {
            path: PathBuf::from(format!("builtin:{name}")),
        });
    }
    Ok(scene)
}

/// Grid side of `builtin:wave` for about `prims` triangles.
pub fn wave_side(prims: usize) -> usize {
    (((prims as f64 / 2.0).sqrt()).round() as usize + 1).max(2)
}

/// Triangles of the `side × side` grid of `builtin:wave` (two per cell, row-major).
pub fn wave_indices(side: usize) -> Vec<[u32; 3]> {
    let mut out = Vec::with_capacity(2 * (side - 1) * (side - 1));
    for y in 0..side - 1 {
        for x in 0..side - 1 {
            let i = (y * side + x) as u32;
            let (r, d) = (i + 1, i + side as u32);
            out.push([i, r, d]);
            out.push([r, d + 1, d]);
        }
    }
    out
}

/// Vertices of `builtin:wave` at `frame` (time `t = frame / FRAMES_PER_SECOND`): grid point
/// `(u, v)` of the unit square rises by `0.08 · sin(2π(3u − t)) · cos(2π(2v + t/2))`, then
/// turns about the line `y = 0.5, z = 0` by `1.5 · t · (u − 0.5)` radians (a twist that
/// tightens over time, so a tree refitted from frame 0 loosens frame by frame).
pub fn wave_vertices(side: usize, frame: u32) -> Vec<Vec3> {
    let t = frame as f32 / FRAMES_PER_SECOND;
    let tau = std::f32::consts::TAU;
    let step = 1.0 / (side - 1) as f32;
    (0..side * side)
        .map(|i| {
            let (u, v) = ((i % side) as f32 * step, (i / side) as f32 * step);
            let z = 0.08 * (tau * (3.0 * u - t)).sin() * (tau * (2.0 * v + 0.5 * t)).cos();
            let (s, c) = (1.5 * t * (u - 0.5)).sin_cos();
            let y = v - 0.5;
            Vec3::new(u, 0.5 + c * y - s * z, s * y + c * z)
        })
        .collect()
}

/// The hard-case generators (see [`generate`]).
fn hard(kind: &str, name: &str, opts: &SceneOptions) -> Result<Mesh, SceneError> {
    let default = match kind {
        "one-big" => 1_000_001,
        "same-cell" => (1 << 21) + 3,
        _ => HARD_DEFAULT_PRIMS,
    };
    let n = opts.prims.unwrap_or(default);
    let mut rng = Pcg32::new(opts.seed, 100 + kind.len() as u64);
    let mut s = Soup::with_capacity(n);
    let mut dropped = 0;
    match kind {
        "point" => {
            let p = Vec3::new(1.5, -2.25, 3.0);
            for _ in 0..n {
                s.tri(p, p, p);
            }
        }
        "plane-x" | "plane-y" | "plane-z" => {
            let axis = (kind.as_bytes()[6] - b'x') as usize;
            uniform(&mut s, n, &mut rng);
            for v in &mut s.vertices {
                v[axis] = 5.0;
            }
        }
        "far" => {
            let base = Vec3::splat(1.0e7);
            for _ in 0..n {
                let c = base + rng.vec3(Vec3::ZERO, Vec3::splat(100.0));
                small_tri(&mut s, &mut rng, c, 1e-3);
            }
        }
        "huge" => {
            let h = Vec3::splat(f32::MAX / 2.0);
            for _ in 0..n {
                s.tri(rng.vec3(-h, h), rng.vec3(-h, h), rng.vec3(-h, h));
            }
        }
        "tiny" | "subnormal" => {
            let (lo, hi) = if kind == "tiny" {
                (f32::MIN_POSITIVE, 16.0 * f32::MIN_POSITIVE)
            } else {
                (0.0, f32::MIN_POSITIVE)
            };
            // The largest value below `hi`: coordinates stay in [lo, hi).
            let top = Vec3::splat(f32::from_bits(hi.to_bits() - 1));
            let (lo, hi) = (Vec3::splat(lo), Vec3::splat(hi));
            for _ in 0..n {
                // Drawn in [0, 1) and scaled: exact for normals, rounded into subnormals.
                let mut p = || {
                    let u = rng.vec3(Vec3::ZERO, Vec3::ONE);
                    (lo + u * (hi - lo)).min(top)
                };
                let (a, b, c) = (p(), p(), p());
                s.tri(a, b, c);
            }
        }
        "needles" => {
            for i in 0..n {
                let a = rng.vec3(Vec3::ZERO, Vec3::ONE);
                match i % 3 {
                    0 if i % 2 == 0 => s.tri(a, a, rng.vec3(Vec3::ZERO, Vec3::ONE)),
                    0 => {
                        // Collinear along an axis: exactly zero area in f32 too.
                        let mut d = Vec3::ZERO;
                        d[(rng.next_u32() % 3) as usize] = rng.range(0.01, 0.1);
                        s.tri(a, a + d, a + 2.0 * d);
                    }
                    _ => {
                        let d = rng.signed3().normalize_or(Vec3::X);
                        let w = d.any_orthonormal_vector() * 1e-7;
                        s.tri(a, a + d, a + w);
                    }
                }
            }
        }
        "one-big" => {
            let side = 100.0f32;
            s.tri(
                Vec3::new(-side, -side, -side),
                Vec3::new(3.0 * side, -side, side),
                Vec3::new(-side, 3.0 * side, 3.0 * side),
            );
            for _ in 1..n {
                let c = rng.vec3(Vec3::ZERO, Vec3::splat(side));
                small_tri(&mut s, &mut rng, c, 1e-3);
            }
        }
        "same-cell" => {
            s.tri(Vec3::ZERO, Vec3::splat(1e-3), Vec3::new(1e-3, 0.0, 0.0));
            s.tri(
                Vec3::ONE,
                Vec3::splat(1.0 - 1e-3),
                Vec3::new(1.0, 1.0, 1.0 - 1e-3),
            );
            let cell = Vec3::splat(0.5);
            let size = Vec3::splat(1.0 / (1u32 << 23) as f32);
            for _ in 2..n.max(2) {
                let a = rng.vec3(cell, cell + size);
                let b = rng.vec3(cell, cell + size);
                let c = rng.vec3(cell, cell + size);
                s.tri(a, b, c);
            }
        }
        "elongated" => {
            uniform(&mut s, n, &mut rng);
            for v in &mut s.vertices {
                *v = Vec3::new(v.x * 1e3, v.y * 1e-2, v.z * 1e-2);
            }
        }
        "nonfinite" => {
            uniform(&mut s, n, &mut rng);
            let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
            for v in &mut s.vertices {
                if rng.next_u32().is_multiple_of(100) {
                    let axis = (rng.next_u32() % 3) as usize;
                    v[axis] = bad[(rng.next_u32() % 3) as usize];
                }
            }
            let verts = &s.vertices;
            let before = s.indices.len();
            s.indices
                .retain(|t| t.iter().all(|&i| verts[i as usize].is_finite()));
            dropped = before - s.indices.len();
        }
        "duplicates" => {
            for _ in 0..n {
                s.tri(Vec3::ZERO, Vec3::X, Vec3::Y);
            }
        }
        _ => return Err(SceneError::UnknownBuiltin(name.to_string())),
    }
    if s.indices.is_empty() {
        return Err(SceneError::AllNonFinite {
            path: PathBuf::from(format!("builtin:{name}")),
            dropped,
        });
    }
    let mut scene = s.into_scene(format!("builtin:{name}"));
    scene.dropped_nonfinite = dropped;
    Ok(scene)
}

/// The icosphere level for a requested size (see [`generate`]).
pub fn sphere_level(prims: Option<usize>) -> u32 {
    let Some(n) = prims else { return 7 };
    (0..=10u32)
        .min_by_key(|&l| (20usize << (2 * l)).abs_diff(n))
        .unwrap_or(0)
}

/// PCG32 (XSH-RR, 64-bit state): small, fast and identical on every platform.
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    const MUL: u64 = 6_364_136_223_846_793_005;

    /// A generator from a seed and a stream number.
    pub fn new(seed: u64, stream: u64) -> Pcg32 {
        let mut r = Pcg32 {
            state: 0,
            inc: (stream << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    /// The next 32 random bits.
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MUL).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1) with 24 random bits (exact in `f32`).
    #[inline]
    pub fn f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    /// Uniform in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }

    /// Log-uniform in [lo, hi) (both positive).
    #[inline]
    pub fn log_range(&mut self, lo: f32, hi: f32) -> f32 {
        lo * (hi / lo).powf(self.f32())
    }

    /// A point uniform in the box [lo, hi).
    #[inline]
    pub fn vec3(&mut self, lo: Vec3, hi: Vec3) -> Vec3 {
        Vec3::new(
            self.range(lo.x, hi.x),
            self.range(lo.y, hi.y),
            self.range(lo.z, hi.z),
        )
    }

    /// A point uniform in [-1, 1)^3.
    #[inline]
    pub fn signed3(&mut self) -> Vec3 {
        self.vec3(Vec3::splat(-1.0), Vec3::splat(1.0))
    }
}

/// A triangle soup under construction: every triangle gets its own three vertices.
struct Soup {
    vertices: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
}

impl Soup {
    fn with_capacity(n: usize) -> Soup {
        Soup {
            vertices: Vec::with_capacity(3 * n),
            indices: Vec::with_capacity(n),
        }
    }

    fn len(&self) -> usize {
        self.indices.len()
    }

    #[inline]
    fn tri(&mut self, a: Vec3, b: Vec3, c: Vec3) {
        let i = self.vertices.len() as u32;
        self.vertices.extend([a, b, c]);
        self.indices.push([i, i + 1, i + 2]);
    }

    /// A quad a-b-c-d (in order around it) as two triangles.
    #[inline]
    fn quad(&mut self, a: Vec3, b: Vec3, c: Vec3, d: Vec3) {
        self.tri(a, b, c);
        self.tri(a, c, d);
    }

    fn into_scene(self, name: String) -> Mesh {
        Mesh {
            name,
            vertices: self.vertices,
            indices: self.indices,
            dropped_nonfinite: 0,
        }
    }
}

/// A random small triangle around `centre` with vertices within `size/2` per axis.
#[inline]
fn small_tri(s: &mut Soup, rng: &mut Pcg32, centre: Vec3, size: f32) {
    let h = 0.5 * size;
    let a = centre + h * rng.signed3();
    let b = centre + h * rng.signed3();
    let c = centre + h * rng.signed3();
    s.tri(a, b, c);
}

/// `uniform`: `n` small random triangles with centres uniform in the cube [0, 100]^3; each
/// triangle spans about half the mean spacing.
fn uniform(s: &mut Soup, n: usize, rng: &mut Pcg32) {
    let side = 100.0f32;
    let size = side * (n as f32).powf(-1.0 / 3.0);
    for _ in 0..n {
        let c = rng.vec3(Vec3::ZERO, Vec3::splat(side));
        small_tri(s, rng, c, size);
    }
}

/// `stadium` (Y up): a 1000 × 1000 ground grid of big quads (~1% of the triangles), a ring of
/// stands of sloped quads between radius 200 and 400 (~4%), and a dense ball of tiny triangles
/// of radius 1 at the centre (the rest).
fn stadium(s: &mut Soup, n: usize, rng: &mut Pcg32) {
    // Ground: g × g quads.
    let g = ((n / 200) as f64).sqrt().max(1.0) as usize;
    let half = 500.0f32;
    let cell = 2.0 * half / g as f32;
    for i in 0..g {
        for j in 0..g {
            let x0 = -half + i as f32 * cell;
            let z0 = -half + j as f32 * cell;
            let (x1, z1) = (x0 + cell, z0 + cell);
            s.quad(
                Vec3::new(x0, 0.0, z0),
                Vec3::new(x1, 0.0, z0),
                Vec3::new(x1, 0.0, z1),
                Vec3::new(x0, 0.0, z1),
            );
        }
    }
    // Stands: `tiers` rings of `segments` sloped quads.
    let quads = (n / 50).max(4);
    let tiers = ((quads / 8) as f64).sqrt().max(1.0) as usize;
    let segments = (quads / tiers).max(4);
    let (r0, r1, top) = (200.0f32, 400.0f32, 80.0f32);
    for t in 0..tiers {
        let (fa, fb) = (t as f32 / tiers as f32, (t + 1) as f32 / tiers as f32);
        let (ra, rb) = (r0 + (r1 - r0) * fa, r0 + (r1 - r0) * fb);
        let (ya, yb) = (top * fa, top * fb);
        for k in 0..segments {
            let a0 = std::f32::consts::TAU * k as f32 / segments as f32;
            let a1 = std::f32::consts::TAU * (k + 1) as f32 / segments as f32;
            let p = |r: f32, y: f32, a: f32| Vec3::new(r * a.cos(), y, r * a.sin());
            s.quad(p(ra, ya, a0), p(ra, ya, a1), p(rb, yb, a1), p(rb, yb, a0));
        }
    }
    // The tiny dense object: the remaining triangles inside a ball of radius 1 above the centre.
    let rest = n.saturating_sub(s.len());
    let size = 2.0 * (rest.max(1) as f32).powf(-1.0 / 3.0);
    let centre = Vec3::new(0.0, 1.5, 0.0);
    let mut made = 0;
    while made < rest {
        let p = rng.signed3();
        if p.length_squared() <= 1.0 {
            small_tri(s, rng, centre + p, size);
            made += 1;
        }
    }
}

/// `city` (Z up): a ground of [`CITY_LENGTH`] × 2/3 of it (2 triangles), boxes of buildings with
/// footprints log-uniform in [2, 200] m and heights log-uniform in [3, [`CITY_MAX_HEIGHT`]] m,
/// walls split per 4 m floor (8 triangles per floor + 2 for the roof), and small street props
/// (single triangles of about 0.5 m) to reach exactly `n`. Extent ratio x : z ≥ 150.
fn city(s: &mut Soup, n: usize, rng: &mut Pcg32) {
    let (lx, ly) = (CITY_LENGTH, CITY_LENGTH * 2.0 / 3.0);
    s.quad(
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(lx, 0.0, 0.0),
        Vec3::new(lx, ly, 0.0),
        Vec3::new(0.0, ly, 0.0),
    );
    // Buildings take about 90% of the triangles.
    let budget = n - n / 10;
    loop {
        let w = rng.log_range(2.0, 200.0);
        let d = rng.log_range(2.0, 200.0);
        let h = rng.log_range(3.0, CITY_MAX_HEIGHT);
        let floors = (h / 4.0).ceil().max(1.0) as usize;
        let cost = 8 * floors + 2;
        if s.len() + cost > budget {
            break;
        }
        let x0 = rng.range(0.0, lx - w);
        let y0 = rng.range(0.0, ly - d);
        let corners = [
            Vec3::new(x0, y0, 0.0),
            Vec3::new(x0 + w, y0, 0.0),
            Vec3::new(x0 + w, y0 + d, 0.0),
            Vec3::new(x0, y0 + d, 0.0),
        ];
        for f in 0..floors {
            let za = h * f as f32 / floors as f32;
            let zb = h * (f + 1) as f32 / floors as f32;
            for k in 0..4 {
                let (a, b) = (corners[k], corners[(k + 1) % 4]);
                s.quad(
                    a + Vec3::Z * za,
                    b + Vec3::Z * za,
                    b + Vec3::Z * zb,
                    a + Vec3::Z * zb,
                );
            }
        }
        let up = Vec3::Z * h;
        s.quad(
            corners[0] + up,
            corners[1] + up,
            corners[2] + up,
            corners[3] + up,
        );
    }
    while s.len() < n {
        let c = rng.vec3(Vec3::new(1.0, 1.0, 0.3), Vec3::new(lx - 1.0, ly - 1.0, 1.0));
        small_tri(s, rng, c, 0.5);
    }
}

/// `hair`: strands of 32 segments of 0.06 units grown from the upper half of a unit sphere,
/// bending under gravity with random curl; each segment is a ribbon quad 0.002 wide (two
/// needle triangles, aspect about 30:1). Exactly `n` triangles (the last strand may be short,
/// its last segment a single triangle).
fn hair(s: &mut Soup, n: usize, rng: &mut Pcg32) {
    const SEGMENTS: usize = 32;
    const STEP: f32 = 0.06;
    const HALF_WIDTH: f32 = 0.001;
    'strands: loop {
        let root = loop {
            let p = rng.signed3();
            let l = p.length();
            if l > 1e-3 && l <= 1.0 && p.y > -0.2 {
                break p / l;
            }
        };
        let mut dir = root;
        let mut p = root;
        for _ in 0..SEGMENTS {
            let turn = 0.25 * rng.signed3() - Vec3::new(0.0, 0.15, 0.0);
            dir = (dir + turn).normalize_or(Vec3::Y);
            let q = p + STEP * dir;
            let side = dir.cross(Vec3::new(0.3, 0.5, 0.8)).normalize_or(Vec3::X) * HALF_WIDTH;
            let (a, b, c, d) = (p - side, p + side, q + side, q - side);
            s.tri(a, b, c);
            if s.len() == n {
                break 'strands;
            }
            s.tri(a, c, d);
            if s.len() == n {
                break 'strands;
            }
            p = q;
        }
    }
}

/// `mixed`: in the cube [0, 10]^3, 1% of the triangles (at least one) are huge (vertices
/// anywhere in the cube); the rest are tiny with sizes log-uniform in [1e-4, 0.1], all in the
/// same place. Exactly `n` triangles, big ones interleaved with small ones.
fn mixed(s: &mut Soup, n: usize, rng: &mut Pcg32) {
    let side = Vec3::splat(10.0);
    let every = 100;
    for i in 0..n {
        if i % every == 0 {
            let (a, b, c) = (
                rng.vec3(Vec3::ZERO, side),
                rng.vec3(Vec3::ZERO, side),
                rng.vec3(Vec3::ZERO, side),
            );
            s.tri(a, b, c);
        } else {
            let c = rng.vec3(Vec3::ZERO, side);
            let size = rng.log_range(1e-4, 0.1);
            small_tri(s, rng, c, size);
        }
    }
}

/// A closed icosphere of radius `r` at the origin: the icosahedron subdivided `level` times
/// (`20·4^level` triangles), shared vertices (watertight: every edge in exactly two
/// triangles), counter-clockwise seen from outside.
pub fn icosphere(level: u32, r: f32) -> Mesh {
    let t = (1.0 + 5.0f64.sqrt()) / 2.0;
    let base: [[f64; 3]; 12] = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    // Work in f64 on the unit sphere; round once at the end.
    let norm = |p: [f64; 3]| {
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        [p[0] / l, p[1] / l, p[2] / l]
    };
    let mut pts: Vec<[f64; 3]> = base.iter().map(|&p| norm(p)).collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(tris.len() * 3 / 2);
        let mut next = Vec::with_capacity(tris.len() * 4);
        let mut midpoint = |a: u32, b: u32, pts: &mut Vec<[f64; 3]>| {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                let (p, q) = (pts[a as usize], pts[b as usize]);
                pts.push(norm([p[0] + q[0], p[1] + q[1], p[2] + q[2]]));
                (pts.len() - 1) as u32
            })
        };
        for &[a, b, c] in &tris {
            let ab = midpoint(a, b, &mut pts);
            let bc = midpoint(b, c, &mut pts);
            let ca = midpoint(c, a, &mut pts);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    let r = r as f64;
    Mesh {
        name: "builtin:sphere".to_string(),
        vertices: pts
            .iter()
            .map(|p| Vec3::new((p[0] * r) as f32, (p[1] * r) as f32, (p[2] * r) as f32))
            .collect(),
        indices: tris,
        dropped_nonfinite: 0,
    }
}
