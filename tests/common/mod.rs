//! Shared helpers of the emc test suite: the standard extents and layouts every exhaustive test
//! walks, hard-case scenes, proptest strategies and the value-ordered walk over all `f32`.
//! Generic on purpose: any test file of the suite may add helpers here.

use emc_core::{Aabb, Backend, Channel, Expander, Frame, Layout, LayoutSpec, SizeTransform};
use glam::Vec3;
use proptest::prelude::*;

/// The scene extents adaptive layouts are resolved on: cube, flat slab, long bar, the
/// reference table's 100×10×1, a flat scene with a zero axis, a needle, and a line (one axis
/// owns every spatial bit: 58 or 64 bits in one channel).
pub const EXTENTS: [[f64; 3]; 7] = [
    [1.0, 1.0, 1.0],
    [4.0, 4.0, 1.0],
    [16.0, 1.0, 1.0],
    [100.0, 10.0, 1.0],
    [1.0, 1.0, 0.0],
    [1e6, 1.0, 1.0],
    [0.0, 3.0, 0.0],
];

/// Custom patterns beyond the standard names: regular ones (magic applies), irregular ones,
/// single channels, full 32-bit channels and the 64-position maximum.
pub const CUSTOM_PATTERNS: [&str; 10] = [
    "custom:xyzs",
    "custom:s",
    "custom:zyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyxzyx",
    "custom:xyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxyxy",
    "custom:szyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyxszyx:linear",
    "custom:xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx",
    "custom:xxyszzxxyzsyyzxszyx",
    "custom:zzzzzzzzzzzzzzzzzzzzzzzzzzzzzzzzssssssssssssssssssssssssssssssss",
    "custom:yyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx",
    "custom:sxsyszsxxxyyyzzzsssxyzxyzxyzyzyzyzzzzzzxxxxxxyyyyyyyssxyzzzzxy",
];

/// Every distinct concrete layout the suite checks: each standard name resolved on every
/// extent of [`EXTENTS`] (duplicates removed), then the [`CUSTOM_PATTERNS`]. Each entry carries
/// a label saying where it came from.
pub fn all_layouts() -> Vec<(String, Layout)> {
    let mut out: Vec<(String, Layout)> = Vec::new();
    for spec in LayoutSpec::STANDARD {
        for e in EXTENTS {
            let l = spec.resolve(e);
            if !out
                .iter()
                .any(|(_, o)| o.channels() == l.channels() && o.transform() == l.transform())
            {
                out.push((format!("{spec} on {e:?}: {l}"), l));
            }
        }
    }
    for name in CUSTOM_PATTERNS {
        let spec: LayoutSpec = name.parse().expect("custom pattern parses");
        let l = spec.resolve([1.0; 3]);
        out.push((format!("{spec}: {l}"), l));
    }
    out
}

/// Every backend except the reference that can serve `layout` on this CPU.
pub fn fast_expanders(layout: &Layout) -> Vec<Expander> {
    Backend::ALL
        .into_iter()
        .filter(|&b| b != Backend::Reference)
        .filter_map(|b| Expander::new(b, layout))
        .collect()
}

/// The reference expander of a layout (the oracle).
pub fn reference(layout: &Layout) -> Expander {
    Expander::new(Backend::Reference, layout).expect("the reference backend is always available")
}

/// `2^bits − 1` (all ones of a channel), 0 for an unused channel.
pub fn ones(bits: u32) -> u64 {
    if bits == 0 {
        0
    } else {
        u64::MAX >> (64 - bits)
    }
}

/// The `f32` with rank `i` in value order: rank 0 and the lowest ranks are negative NaNs, then
/// −∞ … −0.0, +0.0 … +∞, and the highest ranks are positive NaNs. A bijection on `u32`.
#[inline]
pub fn f32_of_rank(i: u32) -> f32 {
    let bits = if i & 0x8000_0000 != 0 {
        i & 0x7FFF_FFFF
    } else {
        !i
    };
    f32::from_bits(bits)
}

/// Inverse of [`f32_of_rank`].
#[inline]
pub fn rank_of_f32(v: f32) -> u32 {
    let b = v.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b | 0x8000_0000
    }
}

/// A box from two corner arrays.
pub fn bx(lo: [f32; 3], hi: [f32; 3]) -> Aabb {
    Aabb::new(Vec3::from(lo), Vec3::from(hi))
}

/// A point box.
pub fn pt(p: [f32; 3]) -> Aabb {
    Aabb::point(Vec3::from(p))
}

/// Named scenes that stress the quantiser: unit cube, huge (1e30) and tiny (1e-30 and
/// subnormal) magnitudes, flat and degenerate scenes, identical primitives, mixed signs.
pub fn hard_scenes() -> Vec<(&'static str, Vec<Aabb>)> {
    let sub = f32::from_bits(1); // smallest subnormal
    vec![
        (
            "unit cube",
            vec![
                bx([0.0; 3], [0.1; 3]),
                bx([0.9; 3], [1.0; 3]),
                bx([0.2, 0.7, 0.4], [0.3, 0.8, 0.45]),
            ],
        ),
        (
            "huge 1e30",
            vec![
                bx([-3e30, -1e30, 0.0], [-2e30, 0.0, 1e29]),
                bx([1e30, 2e30, 5e29], [3e30, 3e30, 6e29]),
                bx([0.0; 3], [1e30; 3]),
            ],
        ),
        (
            "tiny 1e-30",
            vec![
                bx([1e-30, 2e-30, 0.0], [3e-30, 2e-30, 1e-31]),
                bx([4e-30, 5e-30, 2e-31], [5e-30, 9e-30, 3e-31]),
            ],
        ),
        (
            "subnormal",
            vec![
                pt([0.0, 0.0, 0.0]),
                bx([sub, 0.0, 0.0], [f32::from_bits(0x0020_0000), sub, sub]),
                pt([
                    f32::from_bits(0x0030_0000),
                    f32::from_bits(0x0000_1000),
                    0.0,
                ]),
            ],
        ),
        (
            "flat z=0",
            vec![
                bx([0.0, 0.0, 0.0], [1.0, 1.0, 0.0]),
                bx([2.0, 5.0, 0.0], [4.0, 6.0, 0.0]),
            ],
        ),
        (
            "line on x",
            vec![pt([-1.0, 2.0, 3.0]), bx([5.0, 2.0, 3.0], [7.0, 2.0, 3.0])],
        ),
        ("identical", vec![bx([1.0, 2.0, 3.0], [1.5, 2.5, 3.5]); 4]),
        ("single point", vec![pt([-0.0, 0.0, -0.0])]),
        (
            "full f32 range",
            vec![
                bx([-f32::MAX; 3], [-f32::MAX; 3]),
                bx([f32::MAX; 3], [f32::MAX; 3]),
                bx([-1.0; 3], [1.0; 3]),
            ],
        ),
    ]
}

/// A finite `f32` drawn from a mix of ordinary values and hard cases (zeros of both signs,
/// subnormals, 1e±30, the largest finite values).
pub fn finite_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => -10.0f32..10.0,
        1 => Just(0.0f32),
        1 => Just(-0.0f32),
        1 => (1u32..0x0080_0000).prop_map(f32::from_bits),
        1 => (1u32..0x0080_0000).prop_map(|b| -f32::from_bits(b)),
        1 => -1e30f32..1e30,
        1 => -1e-30f32..1e-30,
        1 => prop::sample::select(vec![f32::MAX, -f32::MAX, 1e30, -1e30, 1e-30, f32::MIN_POSITIVE]),
        2 => any::<u32>().prop_map(f32::from_bits).prop_filter("finite", |v| v.is_finite()),
    ]
}

/// A valid, finite primitive box (min ≤ max on every axis) from [`finite_f32`] corners.
pub fn aabb() -> impl Strategy<Value = Aabb> {
    (
        [finite_f32(), finite_f32(), finite_f32()],
        [finite_f32(), finite_f32(), finite_f32()],
    )
        .prop_map(|(a, b)| {
            let (a, b) = (Vec3::from(a), Vec3::from(b));
            Aabb::new(a.min(b), a.max(b))
        })
}

/// A scene of 1..=`max` valid boxes, sometimes forced flat on one axis or made of copies.
pub fn scene(max: usize) -> impl Strategy<Value = Vec<Aabb>> {
    (prop::collection::vec(aabb(), 1..=max), 0u8..6).prop_map(|(mut v, mode)| {
        match mode {
            // Flat on axis `mode`: every box collapses to the plane of the first box's min.
            0..=2 => {
                let a = mode as usize;
                let plane = v[0].min[a];
                for b in &mut v {
                    b.min[a] = plane;
                    b.max[a] = plane;
                }
            }
            // All primitives identical.
            3 => {
                let first = v[0];
                v.iter_mut().for_each(|b| *b = first);
            }
            _ => {}
        }
        v
    })
}

/// A random valid pattern: 1..=64 letters, each channel at most 32 bits.
pub fn pattern() -> impl Strategy<Value = Vec<Channel>> {
    prop::collection::vec(0usize..4, 1..=64).prop_map(|idx| {
        let mut count = [0u32; 4];
        idx.into_iter()
            .map(|i| {
                // Move to the next channel with room; at most 64 letters fit four 32-bit channels.
                let mut c = i;
                while count[c] == 32 {
                    c = (c + 1) % 4;
                }
                count[c] += 1;
                Channel::from_index(c)
            })
            .collect()
    })
}

/// The pattern letters of a channel list (for `custom:` names).
pub fn pattern_letters(chans: &[Channel]) -> String {
    chans.iter().map(|c| c.letter()).collect()
}

/// A layout from a random pattern, with a random size transform.
pub fn layout_of(chans: &[Channel], linear: bool) -> Layout {
    let t = if linear {
        SizeTransform::Linear
    } else {
        SizeTransform::Sqrt
    };
    Layout::from_channels(chans, t).expect("1..=64 channels")
}

/// The frame of a scene, which the generators guarantee is valid.
pub fn frame_of(boxes: &[Aabb]) -> Frame {
    Frame::new(boxes).expect("generated scenes are finite and valid")
}

/// Random and adversarial rays for a triangle list, deterministic in `seed`: random origins
/// and directions, rays aimed exactly at vertices and at points on edges, axis-parallel rays
/// through a vertex's other two coordinates, grazing rays lying in a triangle's plane along
/// one of its edges, and rays starting on a triangle (inside it or at a vertex). Origins are
/// drawn from the scene box padded by 10%, computed in `f64` so huge scenes do not overflow.
pub fn adversarial_rays(
    tris: &[[Vec3; 3]],
    n: usize,
    seed: u64,
) -> Vec<emc_cpu::trace::intersect::Ray> {
    use emc_cpu::scene::builtin::Pcg32;
    use emc_cpu::trace::intersect::Ray;
    let mut rng = Pcg32::new(seed, 7);
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for t in tris {
        for v in t {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a] as f64);
                hi[a] = hi[a].max(v[a] as f64);
            }
        }
    }
    let origin = |rng: &mut Pcg32| {
        let mut o = Vec3::ZERO;
        for a in 0..3 {
            let pad = (hi[a] - lo[a]) * 0.1 + 1e-3 * (1.0 + lo[a].abs().max(hi[a].abs()) * 1e-6);
            let u = rng.f32() as f64;
            let x = (lo[a] - pad) + (hi[a] - lo[a] + 2.0 * pad) * u;
            o[a] = (x as f32).clamp(-f32::MAX, f32::MAX);
        }
        o
    };
    let below = |rng: &mut Pcg32, k: usize| (rng.next_u32() as usize) % k;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let o = origin(&mut rng);
        let t = tris[below(&mut rng, tris.len())];
        let ray = match k % 8 {
            0 => Ray::new(o, rng.signed3()),
            1 => Ray::new(o, t[below(&mut rng, 3)] - o),
            2 => {
                let (a, b) = (t[below(&mut rng, 3)], t[(below(&mut rng, 2) + 1) % 3]);
                let s = rng.f32();
                Ray::new(o, a + (b - a) * s - o)
            }
            3 => {
                let v = t[below(&mut rng, 3)];
                let axis = below(&mut rng, 3);
                let mut o2 = v;
                o2[axis] = o[axis];
                let mut d = Vec3::ZERO;
                d[axis] = if rng.f32() < 0.5 { 1.0 } else { -1.0 };
                Ray::new(o2, d)
            }
            4 => {
                // Grazing: in the triangle's plane, along an edge, starting before it.
                let i = below(&mut rng, 3);
                let (a, b) = (t[i], t[(i + 1) % 3]);
                let d = b - a;
                Ray::new(a - d * rng.range(0.0, 2.0), d)
            }
            5 => {
                // Origin inside the triangle (barycentric point).
                let (u, v) = (rng.f32(), rng.f32());
                let (u, v) = if u + v > 1.0 {
                    (1.0 - u, 1.0 - v)
                } else {
                    (u, v)
                };
                let p = t[0] + (t[1] - t[0]) * u + (t[2] - t[0]) * v;
                Ray::new(p, rng.signed3())
            }
            6 => Ray::new(t[below(&mut rng, 3)], rng.signed3()),
            _ => {
                // One exact zero component in a random direction.
                let mut d = rng.signed3();
                d[below(&mut rng, 3)] = 0.0;
                if d == Vec3::ZERO {
                    d = Vec3::X;
                }
                Ray::new(o, d)
            }
        };
        out.push(ray);
    }
    out
}
