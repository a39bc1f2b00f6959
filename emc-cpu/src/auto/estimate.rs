//! The estimate behind `--layout auto`: each candidate's LBVH headline SAH predicted from one
//! sample of the primitives instead of a full build. The sample is stratified by size: a
//! jittered stratum of the triangle index range (every size class in proportion) plus every
//! triangle among the largest (found by one parallel pass over the boxes), because a few large
//! triangles inside dense clusters of small ones decide most of what size bits buy, and a
//! uniform sample misses them. Per candidate: the codes (emc-core's quantiser arithmetic and
//! expander, bit for bit), a stable radix sort, and one left-to-right sweep that sums the radix
//! tree's inner-node areas. Everything is a fixed function of the boxes: any thread count
//! gives the same sample, codes and sums.
#![forbid(unsafe_code)]

use emc_core::quantize::{position_scale, pow2};
use emc_core::{Aabb, Backend, Channel, Expander, Frame, Layout, SizeTransform};
use glam::Vec3A;
use rayon::prelude::*;

use super::candidates::SizeStats;
use crate::sort::{sort_with_ids, SortError};

/// Seed of the sample's jitter (any fixed value: the choice must not vary between runs).
pub const SEED: u64 = 0xE3C0_A070_2017_0015;

/// One uniform sample triangle per this many triangles of the scene.
pub const UNIFORM_EVERY: usize = 128;
/// Fewest uniform sample triangles (all of a smaller scene).
pub const UNIFORM_MIN: usize = 2048;
/// Most uniform sample triangles.
pub const UNIFORM_MAX: usize = 32_768;
/// Largest triangles taken, per uniform sample triangle.
pub const LARGE_PER_UNIFORM: f64 = 0.25;

/// Dense windows: sub-volumes taken at the scene's full density, whose trees stand in for the
/// deep levels of the full tree that the sparse sample does not reach.
pub const WINDOWS: usize = 3;
const _: () = assert!(WINDOWS <= super::scan::MAX_WINDOWS);
/// Boxes per window, as a multiple of the sample's spacing (scene triangles per sample
/// triangle): the window's trees then hold several levels below the sample's.
pub const WINDOW_PER_SPACING: usize = 4;
/// Fewest boxes per window.
pub const WINDOW_MIN: usize = 512;
/// Most boxes per window.
pub const WINDOW_MAX: usize = 1024;

/// Boxes per task of the pass over all boxes.
const PASS_CHUNK: usize = 1 << 15;

/// A 64-bit mix (SplitMix64's finaliser): the jitter of the strata and the tie breaks.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// `m` indices of `0..n`, one from each of `m` strata of consecutive indices
/// (`[⌊j·n/m⌋, ⌊(j+1)·n/m⌋)`), at a hashed offset inside its stratum (so a mesh whose index
/// order repeats with some period is not sampled in step with it). Strictly ascending; all of
/// `0..n` when `m ≥ n`.
pub fn jittered_sample(n: usize, m: usize, seed: u64) -> Vec<u32> {
    if m >= n {
        return (0..n as u32).collect();
    }
    let bound = |j: usize| ((j as u128 * n as u128) / m as u128) as usize;
    (0..m)
        .map(|j| {
            let (a, b) = (bound(j), bound(j + 1));
            let h = mix64(seed ^ (j as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            (a + ((h as u128 * (b - a) as u128) >> 64) as usize) as u32
        })
        .collect()
}

/// How much a sample of a scene takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SampleSizes {
    /// Uniform strata (all of the scene when at least `n`).
    pub uniform: usize,
    /// Largest triangles.
    pub large: usize,
}

impl SampleSizes {
    /// The sizes for a scene of `n` triangles: one uniform triangle per [`UNIFORM_EVERY`]
    /// (within [`UNIFORM_MIN`]..=[`UNIFORM_MAX`]) and a quarter as many of the largest; a
    /// scene of at most [`UNIFORM_MIN`] is sampled whole (the estimate is then exact).
    pub fn for_scene(n: usize) -> SampleSizes {
        let u = (n / UNIFORM_EVERY).clamp(UNIFORM_MIN, UNIFORM_MAX);
        if u >= n {
            return SampleSizes::whole(n);
        }
        SampleSizes {
            uniform: u,
            large: (u as f64 * LARGE_PER_UNIFORM) as usize,
        }
    }

    /// Every triangle: the estimate is the exact headline SAH.
    pub fn whole(n: usize) -> SampleSizes {
        SampleSizes {
            uniform: n,
            large: 0,
        }
    }
}

/// Per-frame constants of the shared quantised values (see [`Points::q32`]).
#[derive(Clone, Copy, Debug)]
struct Ctx {
    origin: [f64; 3],
    inv_extent: [f64; 3],
    diag: f64,
}

/// A set of sampled boxes with what the candidates' codes need.
#[derive(Clone, Debug, Default)]
pub struct Points {
    /// Triangle ids, ascending.
    pub ids: Vec<u32>,
    /// Per box the position values of a 32-bit channel, `min(⌊u_a · 2^31⌋, 2^32)` with
    /// `u_a = (c2 − 2·o) · fl(1/E)`, and the size values of a 32-bit size channel,
    /// `min(⌊t · 2^32⌋, 2^32)` for `t` = `fl(sqrt(fl(d / D)))` (sqrt) and `fl(d / D)` (linear).
    /// A channel of `n` bits is the value shifted right by `32 − n` and clamped to `2^n − 1`,
    /// bit for bit what emc-core computes: its scale `fl(2^n / E)` is `2^n · fl(1/E)` (checked
    /// once per axis, [`Sample::exact`]), scaling by a power of two commutes with rounding,
    /// and `⌊⌊y · 2^k⌋ / 2^k⌋ = ⌊y⌋`.
    q32: Vec<[u64; 5]>,
    /// `lo + hi` per axis of each box (twice the centre, exact in `f64`).
    c2: Vec<[f64; 3]>,
    /// Each box's corners.
    corners: Vec<(Vec3A, Vec3A)>,
}

impl Points {
    fn gather(boxes: &[Aabb], ids: Vec<u32>, ctx: &Ctx) -> Points {
        let top = 1u64 << 32;
        let mut p = Points {
            c2: Vec::with_capacity(ids.len()),
            q32: Vec::with_capacity(ids.len()),
            corners: Vec::with_capacity(ids.len()),
            ids,
        };
        for &i in &p.ids {
            let b = &boxes[i as usize];
            let c = [
                b.min.x as f64 + b.max.x as f64,
                b.min.y as f64 + b.max.y as f64,
                b.min.z as f64 + b.max.z as f64,
            ];
            let pos = |a: usize| {
                ((((c[a] - 2.0 * ctx.origin[a]) * ctx.inv_extent[a]) * pow2(31)) as u64).min(top)
            };
            let lin = b.diagonal_sq_f64().sqrt() / ctx.diag;
            let t = |v: f64| ((v * pow2(32)) as u64).min(top);
            p.q32.push([pos(0), pos(1), pos(2), t(lin.sqrt()), t(lin)]);
            p.c2.push(c);
            p.corners.push((Vec3A::from(b.min), Vec3A::from(b.max)));
        }
        p
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// The boxes, in id order.
    pub fn boxes(&self) -> Vec<Aabb> {
        self.corners
            .iter()
            .map(|(lo, hi)| Aabb::new((*lo).into(), (*hi).into()))
            .collect()
    }
}

/// The sample a choice rests on: jittered uniform strata of the index range plus the largest
/// triangles of the scene.
#[derive(Clone, Debug)]
pub struct Sample {
    /// Triangles of the scene.
    pub n: usize,
    /// What was asked for.
    pub sizes: SampleSizes,
    /// The points: uniform and largest, ascending ids.
    pub strata: Points,
    /// Of them, from the uniform strata.
    pub uniform: usize,
    /// Of them, taken for being among the largest (and not already a uniform pick).
    pub large: usize,
    /// The squared diagonal a triangle must exceed (or, at a hashed share, reach) to be taken
    /// as large (+inf when none are).
    pub large_d2: f64,
    /// Size quantiles of the uniform part (the generated candidates' size bits follow them).
    pub size_stats: SizeStats,
    /// The dense windows (none when the sample is the whole scene), collected in the pass
    /// that finds the largest: each the boxes nearest
    /// (by centroid, Chebyshev distance) to one uniform sample triangle, all of them.
    pub windows: Vec<Points>,
    /// Mesh triangles per sample triangle: the window tree's nodes of fewer boxes than this
    /// are the deep levels the sample tree does not hold.
    pub spacing: f64,
    /// Per axis: the shift rule of [`Points::q32`] holds for every channel width 1..=32
    /// (else the value is computed from `c2` with the candidate's own scale).
    exact: [bool; 3],
}

impl Sample {
    /// Draw the sample of `boxes` (every box finite and valid, as a frame guarantees) with the
    /// sizes of [`SampleSizes::for_scene`].
    pub fn draw(boxes: &[Aabb], frame: &Frame) -> Sample {
        Sample::draw_sized(boxes, frame, SampleSizes::for_scene(boxes.len()))
    }

    /// Draw the sample with the caller's sizes: the jittered uniform strata, from them the
    /// size threshold of the largest triangles, then one parallel pass over all boxes that
    /// collects the largest (chunks concatenated in order, so the result does not depend on
    /// the thread count).
    pub fn draw_sized(boxes: &[Aabb], frame: &Frame, sizes: SampleSizes) -> Sample {
        let n = boxes.len();
        let mu = sizes.uniform.min(n);
        let uniform = jittered_sample(n, mu, SEED);
        let (o, e) = (frame.origin(), frame.extent());
        let inv_extent = e.map(|v| if v > 0.0 { 1.0 / v } else { 0.0 });
        let ctx = Ctx {
            origin: o,
            inv_extent,
            diag: frame.diagonal(),
        };
        let exact = [0, 1, 2].map(|a| {
            e[a] > 0.0
                && (1..=32).all(|n| position_scale(n, e[a]) * 0.5 == pow2(n - 1) * inv_extent[a])
        });
        let mut d2: Vec<f64> = uniform
            .iter()
            .map(|&i| boxes[i as usize].diagonal_sq_f64())
            .collect();
        d2.sort_by(f64::total_cmp);
        let size_stats = SizeStats::from_sorted_d2(&d2, frame.diagonal());
        let mut large_d2 = f64::INFINITY;
        let mut ids = uniform.clone();
        let mut windows = Vec::new();
        if mu < n && mu > 0 && sizes.large > 0 {
            // The sample's share of the scene above the threshold should be large / n.
            let want = sizes.large as f64 * mu as f64 / n as f64;
            let k = ((mu as f64 - want).ceil().max(0.0) as usize).min(mu - 1);
            let thr = d2[k];
            let above = d2.iter().filter(|&&v| v > thr).count() as f64;
            let equal = d2.iter().filter(|&&v| v == thr).count() as f64;
            // Boxes exactly at the threshold (equal sizes are common in meshes) are taken at
            // the share that makes up the count, by a hash of their index.
            let share = ((want - above) / equal.max(1.0)).clamp(0.0, 1.0);
            let cut = (share * 2f64.powi(64)).min(u64::MAX as f64) as u64;
            let spec = WindowSpec::new(boxes, &uniform, n as f64 / (mu + sizes.large) as f64);
            let (big, found) = largest(boxes, thr, cut, spec.as_ref());
            ids = merge_unique(&uniform, &big);
            large_d2 = thr;
            if let Some(spec) = spec {
                windows = spec
                    .ids(found)
                    .into_iter()
                    .map(|w| Points::gather(boxes, w, &ctx))
                    .collect();
            }
        }
        let large = ids.len() - uniform.len();
        let spacing = n as f64 / ids.len().max(1) as f64;
        Sample {
            n,
            sizes,
            strata: Points::gather(boxes, ids, &ctx),
            uniform: uniform.len(),
            large,
            large_d2,
            size_stats,
            windows,
            spacing,
            exact,
        }
    }

    /// Sampled triangles.
    pub fn len(&self) -> usize {
        self.strata.len()
    }

    /// True when nothing was sampled (an empty scene).
    pub fn is_empty(&self) -> bool {
        self.strata.is_empty()
    }

    /// True when the sample is the whole scene (the estimate is then the exact SAH).
    pub fn is_whole(&self) -> bool {
        self.strata.len() == self.n
    }
}

/// Twice the centroid of a box, exact in `f64`.
#[inline(always)]
fn centre2(b: &Aabb) -> [f64; 3] {
    [
        b.min.x as f64 + b.max.x as f64,
        b.min.y as f64 + b.max.y as f64,
        b.min.z as f64 + b.max.z as f64,
    ]
}

/// Chebyshev distance between two doubled centroids.
#[inline(always)]
fn cheb(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (a[0] - b[0])
        .abs()
        .max((a[1] - b[1]).abs())
        .max((a[2] - b[2]).abs())
}

/// Where the dense windows are: [`WINDOWS`] centres among the uniform sample (one per stratum
/// of it, jittered), each window the `w` boxes nearest to its centre by centroid (Chebyshev
/// distance, ties by id), `w` = [`WINDOW_PER_SPACING`] sample spacings within
/// [`WINDOW_MIN`]..=[`WINDOW_MAX`]. The search radius comes from the uniform sample (twice
/// the distance of its `k`-th nearest point, `k` the sample's share of `w`); the pass over all
/// boxes collects those inside it, and a window whose radius holds fewer than `w` keeps all.
#[derive(Clone, Debug)]
struct WindowSpec {
    w: usize,
    centres: Vec<[f64; 3]>,
    radius: Vec<f64>,
    /// f32 bounds of `min + max` around each centre, widened past the f32 rounding.
    pre: Vec<(Vec3A, Vec3A)>,
}

impl WindowSpec {
    fn new(boxes: &[Aabb], uniform: &[u32], spacing: f64) -> Option<WindowSpec> {
        let n = boxes.len();
        let mu = uniform.len();
        if mu < 2 {
            return None;
        }
        let w = ((WINDOW_PER_SPACING as f64 * spacing) as usize).clamp(WINDOW_MIN, WINDOW_MAX);
        let k = ((w as f64 * mu as f64 / n as f64).ceil() as usize).clamp(1, mu - 1);
        let uc: Vec<[f64; 3]> = uniform
            .iter()
            .map(|&i| centre2(&boxes[i as usize]))
            .collect();
        let centres: Vec<[f64; 3]> = jittered_sample(mu, WINDOWS.min(mu), SEED ^ 0x57)
            .into_iter()
            .map(|j| uc[j as usize])
            .collect();
        let radius: Vec<f64> = centres
            .iter()
            .map(|c| {
                let mut d: Vec<f64> = uc.iter().map(|u| cheb(c, u)).collect();
                d.select_nth_unstable_by(k, f64::total_cmp);
                2.0 * d[k]
            })
            .collect();
        let pre = centres
            .iter()
            .zip(&radius)
            .map(|(c, &r)| {
                let slack = |a: usize| r + (c[a].abs() + r) * 1e-5;
                let v = |sign: f64| {
                    Vec3A::new(
                        (c[0] + sign * slack(0)) as f32,
                        (c[1] + sign * slack(1)) as f32,
                        (c[2] + sign * slack(2)) as f32,
                    )
                };
                (v(-1.0), v(1.0))
            })
            .collect::<Vec<(Vec3A, Vec3A)>>();
        Some(WindowSpec {
            w,
            centres,
            radius,
            pre,
        })
    }

    /// Record box `id` (`b`) in every window whose radius holds it: (window, distance, id).
    #[inline(always)]
    fn hit(&self, b: &Aabb, id: u32, found: &mut Vec<WindowHit>) {
        let c32 = Vec3A::from(b.min) + Vec3A::from(b.max);
        for (wi, &(lo, hi)) in self.pre.iter().enumerate() {
            if !(c32.cmpge(lo) & c32.cmple(hi)).all() {
                continue;
            }
            let d = cheb(&centre2(b), &self.centres[wi]);
            if d <= self.radius[wi] {
                found.push((wi, d, id));
            }
        }
    }

    /// Each window's ids (ascending) from the pass's finds.
    fn ids(&self, found: Vec<WindowHit>) -> Vec<Vec<u32>> {
        let w = self.w;
        let mut by: Vec<Vec<(f64, u32)>> = vec![Vec::new(); self.centres.len()];
        for (wi, d, id) in found {
            by[wi].push((d, id));
        }
        by.into_iter()
            .map(|mut v| {
                // The `w` nearest (ties by id) without sorting them all.
                let by_dist =
                    |a: &(f64, u32), b: &(f64, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
                if v.len() > w {
                    v.select_nth_unstable_by(w, by_dist);
                    v.truncate(w);
                }
                let mut ids: Vec<u32> = v.into_iter().map(|(_, id)| id).collect();
                ids.sort_unstable();
                ids
            })
            .collect()
    }
}

/// A box inside a window's radius: (window, distance, id).
type WindowHit = (usize, f64, u32);

/// One parallel pass over all boxes: the ids (ascending) of those whose squared diagonal is
/// above `thr`, or at it when the id's hash is below `cut`; and with `win` the boxes inside
/// its windows' radii (chunks in order, so neither depends on the thread count).
fn largest(
    boxes: &[Aabb],
    thr: f64,
    cut: u64,
    win: Option<&WindowSpec>,
) -> (Vec<u32>, Vec<WindowHit>) {
    // An f32 prefilter below the threshold by more than its rounding (the squared diagonal in
    // f32 is within 3·2^-24 of the f64 one, relatively): only boxes that pass it are
    // compared exactly.
    let pre = (thr * (1.0 - 1e-6)) as f32;
    let per: Vec<(Vec<u32>, Vec<WindowHit>)> = boxes
        .par_chunks(PASS_CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let base = c * PASS_CHUNK;
            let mut found = Vec::new();
            // The windows' boxes (none without windows), tested per box in the same pass; the
            // few inside are measured exactly by `WindowSpec::hit`.
            let wins: Vec<super::scan::Window> = win.map_or(Vec::new(), |w| {
                w.pre
                    .iter()
                    .map(|(lo, hi)| (lo.to_array(), hi.to_array()))
                    .collect()
            });
            let mut hit = |k: usize| {
                if let Some(ws) = win {
                    ws.hit(&chunk[k], (base + k) as u32, &mut found);
                }
            };
            let mut big = Vec::new();
            let mut take = |k: usize| {
                let s = chunk[k].diagonal_sq_f64();
                if s > thr || (s == thr && cut > 0 && mix64(SEED ^ (base + k) as u64) < cut) {
                    big.push((base + k) as u32);
                }
            };
            // Eight boxes per step: bit masks of the boxes that pass the size prefilter and
            // a window's box ([`super::scan`]).
            super::scan::for_each_block(chunk, pre, &wins, |first, mut mask, mut wmask| {
                while mask != 0 {
                    take(first + mask.trailing_zeros() as usize);
                    mask &= mask - 1;
                }
                while wmask != 0 {
                    hit(first + wmask.trailing_zeros() as usize);
                    wmask &= wmask - 1;
                }
            });
            (big, found)
        })
        .collect();
    let mut big = Vec::new();
    let mut found = Vec::new();
    for (b, f) in per {
        big.extend(b);
        found.extend(f);
    }
    (big, found)
}

/// The sorted union of two ascending id lists.
fn merge_unique(a: &[u32], b: &[u32]) -> Vec<u32> {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        let next = match (a.get(i), b.get(j)) {
            (Some(&x), Some(&y)) if x == y => {
                i += 1;
                j += 1;
                x
            }
            (Some(&x), Some(&y)) if x < y => {
                i += 1;
                x
            }
            (Some(&x), None) => {
                i += 1;
                x
            }
            (_, Some(&y)) => {
                j += 1;
                y
            }
            (None, None) => break,
        };
        out.push(next);
    }
    out
}

/// The quantiser of one layout for the sample: per channel the shift of the 32-bit value and
/// the clamp (see [`Sample::q32`]), or emc-core's own scale on an axis where the shift rule does
/// not hold.
#[derive(Clone, Copy, Debug)]
struct Quant {
    shift: [u32; 4],
    max: [u64; 4],
    /// Which size value the size channel takes: 3 sqrt, 4 linear.
    size_kind: usize,
    origin2: [f64; 3],
    half_scale: [f64; 3],
    exact: [bool; 3],
}

impl Quant {
    fn new(layout: &Layout, frame: &Frame, exact: [bool; 3]) -> Quant {
        let (o, e) = (frame.origin(), frame.extent());
        let mut q = Quant {
            shift: [32; 4],
            max: [0; 4],
            size_kind: match layout.transform() {
                SizeTransform::Sqrt => 3,
                SizeTransform::Linear => 4,
            },
            origin2: [0.0; 3],
            half_scale: [0.0; 3],
            exact,
        };
        for c in Channel::ALL {
            let n = layout.bits(c);
            q.shift[c.index()] = 32 - n.min(32);
            q.max[c.index()] = layout.channel_max(c);
        }
        for a in 0..3 {
            let n = layout.bits(Channel::from_index(a));
            q.origin2[a] = 2.0 * o[a];
            if e[a] > 0.0 && n > 0 {
                q.half_scale[a] = position_scale(n, e[a]) * 0.5;
                // Wider channels (a named adaptive layout on a line scene) need the full
                // arithmetic: the shared values hold 32 bits.
                q.exact[a] &= n <= 32;
            } else {
                // A flat axis or one without bits: the value is 0 either way.
                q.exact[a] = true;
            }
        }
        q
    }

    /// The four channel values of point `i` (emc-core's normative values).
    #[inline(always)]
    fn quantize(&self, s: &Points, i: usize) -> [u64; 4] {
        let v = &s.q32[i];
        let p = |a: usize| {
            if self.exact[a] {
                (v[a] >> self.shift[a]).min(self.max[a])
            } else {
                (((s.c2[i][a] - self.origin2[a]) * self.half_scale[a]) as u64).min(self.max[a])
            }
        };
        let size = (v[self.size_kind] >> self.shift[3]).min(self.max[3]);
        [p(0), p(1), p(2), size]
    }
}

/// The expander backend of the estimate: `pdep` where it is fast, else byte tables.
pub fn estimate_backend() -> Backend {
    if emc_core::cpu::fast_pdep() {
        Backend::Pdep
    } else {
        Backend::Table
    }
}

/// Buffers of one estimate, kept between candidates.
#[derive(Debug, Default)]
pub struct Scratch {
    codes: Vec<u64>,
    ids: Vec<u32>,
    kbuf: Vec<u64>,
    vbuf: Vec<u32>,
    stack: Vec<(u32, Vec3A, Vec3A, u32)>,
}

/// Half the surface area of a box given by its corners, in `f64` from `f64` differences (so
/// that neither scenes near `f32::MAX` nor subnormal ones lose it; 0 for a flat box).
#[inline(always)]
fn half_area(lo: Vec3A, hi: Vec3A) -> f64 {
    let d = |a: usize| (hi[a] as f64 - lo[a] as f64).max(0.0);
    let (x, y, z) = (d(0), d(1), d(2));
    x * y + y * z + z * x
}

/// Split level between sorted positions `p` and `p + 1` over the index-augmented key (64 key
/// bits above 32 position bits), as Karras' radix tree orders its splits: the tree is the
/// Cartesian tree of these levels.
#[inline(always)]
fn level(keys: &[u64], p: usize) -> u32 {
    let x = keys[p] ^ keys[p + 1];
    if x != 0 {
        32 + (63 - x.leading_zeros())
    } else {
        let q = p as u32;
        31 - (q ^ (q + 1)).leading_zeros()
    }
}

/// Headline-SAH terms of one radix tree over points (one primitive per leaf).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TreeAreas {
    /// Sum of the inner nodes' half areas (root included).
    pub inner: f64,
    /// Of them, the inner nodes over fewer points than the sweep's cut.
    pub deep: f64,
    /// Sum of the leaves' half areas.
    pub leaves: f64,
    /// Half area of the root.
    pub root: f64,
    /// Primitives.
    pub prims: usize,
}

impl TreeAreas {
    /// The headline SAH (`Ct = Ci = 1`, one primitive per leaf); a root of zero area counts
    /// every node alike, as `bvh::sah_cost` does.
    pub fn sah(&self) -> f64 {
        if self.root > 0.0 {
            (self.inner + self.leaves) / self.root
        } else {
            (2 * self.prims).saturating_sub(1) as f64
        }
    }
}

/// Codes of `points` under `layout` in `frame` into `out` (equal to emc-core's encoder).
pub fn point_codes(
    sample: &Sample,
    points: &Points,
    layout: &Layout,
    frame: &Frame,
    backend: Backend,
    out: &mut Vec<u64>,
) {
    let q = Quant::new(layout, frame, sample.exact);
    // Pdep and tables serve every layout (tables always; pdep where the CPU has BMI2, which
    // `estimate_backend` checked); the reference loop is the last resort.
    let exp = Expander::new(backend, layout)
        .or_else(|| Expander::new(Backend::Table, layout))
        .or_else(|| Expander::new(Backend::Reference, layout));
    out.clear();
    match exp {
        Some(e) => out.extend((0..points.len()).map(|i| e.expand(q.quantize(points, i)))),
        None => out.resize(points.len(), 0),
    }
}

/// The radix tree of the points at sorted positions `order` (codes `keys`, in that order):
/// one left-to-right sweep that closes every subtree at its split.
fn sweep(
    points: &Points,
    keys: &[u64],
    order: &[u32],
    cut: f64,
    stack: &mut Vec<(u32, Vec3A, Vec3A, u32)>,
) -> TreeAreas {
    let m = keys.len();
    let mut t = TreeAreas {
        prims: m,
        ..TreeAreas::default()
    };
    stack.clear();
    let (mut root_lo, mut root_hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
    for (p, &id) in order.iter().enumerate() {
        let (mut lo, mut hi) = points.corners[id as usize];
        let mut count = 1u32;
        t.leaves += half_area(lo, hi);
        root_lo = root_lo.min(lo);
        root_hi = root_hi.max(hi);
        let l = if p + 1 < m { level(keys, p) } else { u32::MAX };
        // Close every open subtree whose split is below this one: its right part ends here.
        while let Some(&(tl, tlo, thi, tc)) = stack.last() {
            if tl >= l {
                break;
            }
            stack.pop();
            lo = lo.min(tlo);
            hi = hi.max(thi);
            count += tc;
            let a = half_area(lo, hi);
            t.inner += a;
            if (count as f64) < cut {
                t.deep += a;
            }
        }
        if p + 1 < m {
            stack.push((l, lo, hi, count));
        }
    }
    t.root = half_area(root_lo, root_hi);
    t
}

/// A candidate's estimate: the headline SAH of the full tree, its upper levels from the
/// radix tree over the sample and its deep levels from the trees over the dense windows.
///
/// The sample tree's inner nodes stand for the full tree's nodes of at least one sample
/// spacing of triangles (a node over `k` sample points bounds about the `k · spacing`
/// triangles of the full node). The full tree's nodes below that are seen in the windows at
/// the scene's own density: their inner nodes over fewer than one spacing of boxes, scaled by
/// scene triangles per window box. On a dense cube of overlapping boxes only these deep levels
/// tell the size bits apart; on the shared scenes the sample tree's ranking holds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Estimate {
    /// The tree over the sample.
    pub strata: TreeAreas,
    /// The windows' trees, summed (`deep` over nodes below one sample spacing).
    pub windows: TreeAreas,
    /// Triangles of the scene.
    pub prims: usize,
}

impl Estimate {
    /// The estimated headline SAH (`Ct = Ci = 1`, one triangle per leaf) of the sample tree
    /// alone: the upper levels. Exact when the sample is the whole scene.
    pub fn sah(&self) -> f64 {
        self.strata.sah()
    }

    /// The estimate with the deep levels, when the windows were measured: the sample tree's
    /// inner areas, the windows' deep areas scaled to the scene and the sample's leaves
    /// scaled to the scene, over the sample root.
    pub fn dense_sah(&self) -> Option<f64> {
        let s = &self.strata;
        if self.windows.prims == 0 || s.prims == 0 || s.root <= 0.0 {
            return None;
        }
        let n = self.prims as f64;
        let deep = self.windows.deep * n / self.windows.prims as f64;
        let leaves = s.leaves * n / s.prims as f64;
        Some((s.inner + deep + leaves) / s.root)
    }
}

/// The estimate of one layout on the sample: codes, one stable radix sort, one sweep. One
/// thread's work in a fixed order.
pub fn estimate(
    sample: &Sample,
    layout: &Layout,
    frame: &Frame,
    backend: Backend,
    s: &mut Scratch,
) -> Result<Estimate, SortError> {
    let pts = &sample.strata;
    if pts.is_empty() {
        return Ok(Estimate::default());
    }
    point_codes(sample, pts, layout, frame, backend, &mut s.codes);
    sort_with_ids(&mut s.codes, &mut s.ids, &mut s.kbuf, &mut s.vbuf)?;
    let strata = sweep(pts, &s.codes, &s.ids, 0.0, &mut s.stack);
    Ok(Estimate {
        strata,
        windows: TreeAreas::default(),
        prims: sample.n,
    })
}

/// The windows' trees of one layout (codes, sort and sweep per window, summed), for
/// [`Estimate::windows`]. One thread's work in a fixed order.
pub fn estimate_windows(
    sample: &Sample,
    layout: &Layout,
    frame: &Frame,
    backend: Backend,
    s: &mut Scratch,
) -> Result<TreeAreas, SortError> {
    let mut windows = TreeAreas::default();
    for w in &sample.windows {
        if w.is_empty() {
            continue;
        }
        point_codes(sample, w, layout, frame, backend, &mut s.codes);
        sort_with_ids(&mut s.codes, &mut s.ids, &mut s.kbuf, &mut s.vbuf)?;
        let t = sweep(w, &s.codes, &s.ids, sample.spacing, &mut s.stack);
        windows.inner += t.inner;
        windows.deep += t.deep;
        windows.leaves += t.leaves;
        windows.root += t.root;
        windows.prims += t.prims;
    }
    Ok(windows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use emc_core::glam::Vec3;
    use emc_core::{Encoder, LayoutSpec};

    fn boxes(n: usize) -> Vec<Aabb> {
        (0..n)
            .map(|i| {
                let h = mix64(i as u64);
                let c = Vec3::new(
                    (h & 0xFFFF) as f32,
                    ((h >> 16) & 0xFFFF) as f32 * 0.25,
                    ((h >> 32) & 0xFFFF) as f32 * 0.01,
                );
                let r = if i % 37 == 0 {
                    5000.0
                } else {
                    ((h >> 48) % 7) as f32 + 0.5
                };
                Aabb::new(c - Vec3::splat(r), c + Vec3::splat(r))
            })
            .collect()
    }

    #[test]
    fn strata_are_strictly_ascending_and_cover_the_range() {
        for (n, m) in [(10, 3), (1000, 999), (500_000, 16_384), (7, 7), (7, 100)] {
            let s = jittered_sample(n, m, SEED);
            assert_eq!(s.len(), m.min(n));
            assert!(s.windows(2).all(|w| w[0] < w[1]), "n {n} m {m}");
            assert!(s.iter().all(|&i| (i as usize) < n));
        }
    }

    #[test]
    fn point_codes_equal_the_encoder() {
        let b = boxes(20_000);
        let frame = Frame::new(&b).unwrap();
        let sample = Sample::draw(&b, &frame);
        assert!(!sample.is_whole() && sample.large > 0);
        assert!(Sample::draw(&b[..UNIFORM_MIN], &frame).is_whole());
        for spec in [
            "morton63",
            "emc64-sort",
            "emc64-var",
            "emc32-var",
            "custom:xyzsxxyzs:linear",
            "custom:xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyss",
        ] {
            let spec: LayoutSpec = spec.parse().unwrap();
            let layout = spec.resolve(frame.extent());
            let enc = Encoder::for_layout(layout, &frame);
            for points in [&sample.strata] {
                let pb = points.boxes();
                let mut want = vec![0u64; pb.len()];
                enc.encode_batch(&pb, &mut want).unwrap();
                for backend in [Backend::Table, Backend::Reference, estimate_backend()] {
                    let mut got = Vec::new();
                    point_codes(&sample, points, &layout, &frame, backend, &mut got);
                    assert_eq!(got, want, "{spec} {backend:?}");
                }
            }
        }
    }

    #[test]
    fn windows_are_the_nearest_boxes_at_full_density() {
        let b = boxes(100_000);
        let frame = Frame::new(&b).unwrap();
        let s = Sample::draw(&b, &frame);
        assert_eq!(s.windows.len(), WINDOWS);
        let w = ((WINDOW_PER_SPACING as f64 * s.n as f64 / (s.uniform + s.sizes.large) as f64)
            as usize)
            .clamp(WINDOW_MIN, WINDOW_MAX);
        let uniform = jittered_sample(s.n, s.sizes.uniform.min(s.n), SEED);
        let spec = WindowSpec::new(
            &b,
            &uniform,
            s.n as f64 / (s.uniform + s.sizes.large) as f64,
        )
        .unwrap();
        for (win, c) in s.windows.iter().zip(&spec.centres) {
            assert!(win.len() == w, "{} boxes, want {w}", win.len());
            assert!(win.ids.windows(2).all(|p| p[0] < p[1]));
            // Every box outside is at least as far from the centre as the farthest inside:
            // the window is the scene at full density, nothing in between skipped.
            let members: std::collections::HashSet<u32> = win.ids.iter().copied().collect();
            let far = win
                .ids
                .iter()
                .map(|&j| cheb(c, &centre2(&b[j as usize])))
                .fold(0.0, f64::max);
            assert!(far > 0.0);
            for (i, bx) in b.iter().enumerate() {
                if !members.contains(&(i as u32)) {
                    assert!(cheb(c, &centre2(bx)) >= far, "box {i} skipped");
                }
            }
        }
        // The same windows at one and at two threads.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let s1 = one.install(|| Sample::draw(&b, &frame));
        let ids = |s: &Sample| s.windows.iter().map(|w| w.ids.clone()).collect::<Vec<_>>();
        assert_eq!(ids(&s1), ids(&s));
    }

    #[test]
    fn large_boxes_are_all_taken() {
        let b = boxes(400_000);
        let frame = Frame::new(&b).unwrap();
        let s = Sample::draw(&b, &frame);
        let sz = SampleSizes::for_scene(b.len());
        assert_eq!(s.uniform, sz.uniform);
        // Every 37th box is huge (about 10,800 of them, all of one size); the threshold sits
        // among them and takes about `large` boxes at it.
        assert!(
            s.large > sz.large / 2 && s.large < 2 * sz.large,
            "{} vs {}",
            s.large,
            sz.large
        );
        let taken: std::collections::HashSet<u32> = s.strata.ids.iter().copied().collect();
        for (i, bx) in b.iter().enumerate() {
            if bx.diagonal_sq_f64() > s.large_d2 {
                assert!(
                    taken.contains(&(i as u32)),
                    "box {i} is large but not sampled"
                );
            }
        }
    }
}
