//! Property checks over arbitrary bytes, shared by the `cargo fuzz` targets (in `fuzz/`) and
//! the test that replays their corpora: each function decodes its input, runs one stage of the
//! pipeline and panics when a promised property fails. Bad input must give an error, not a panic.
#![forbid(unsafe_code)]

use std::path::Path;

use emc_core::{Aabb, Backend, Channel, Encoder, Frame, Layout, LayoutSpec, SizeTransform};
use glam::Vec3;

use crate::build::{build_scene, Builder, PipelineOptions};
use crate::bvh::refit::CollapseParams;
use crate::scene::obj::parse_obj_bytes;
use crate::scene::Mesh;
use crate::trace::intersect::{brute_force_closest, brute_force_occluded, Ray};
use crate::trace::Accel;

/// A byte reader that yields zeros once the input is exhausted.
#[derive(Debug)]
struct Bytes<'a>(&'a [u8]);

impl Bytes<'_> {
    fn u8(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.u8(), self.u8(), self.u8(), self.u8()])
    }
    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// An error message must be one non-empty line.
fn one_line(msg: &str) {
    assert!(
        !msg.is_empty() && !msg.contains('\n'),
        "error is not one line: {msg:?}"
    );
}

/// OBJ front end: the bytes parse into a scene that keeps the documented invariants (at least
/// one triangle, indices in range, used vertices finite, dropped count consistent) or into a
/// one-line error; the line check alone agrees with the full parse on malformed lines.
pub fn check_obj(data: &[u8]) {
    let path = Path::new("fuzz.obj");
    match parse_obj_bytes(data, path, "fuzz".into()) {
        Ok(s) => {
            assert!(s.triangle_count() > 0, "a scene without triangles loaded");
            for t in &s.indices {
                for &i in t {
                    assert!((i as usize) < s.vertices.len(), "index {i} out of range");
                    assert!(s.vertices[i as usize].is_finite(), "non-finite vertex kept");
                }
            }
            assert!(
                crate::scene::obj::check_obj_bytes(data, path).is_ok(),
                "line check refuses a file the parser loads"
            );
        }
        Err(e) => one_line(&e.to_string()),
    }
}

/// Layout parsing: a spec that parses prints back to itself, resolves on any extent to a layout
/// of at most 64 positions whose masks are disjoint and count its bits, and a layout rebuilt from
/// its channels is the same; a refused spec gives a one-line error.
pub fn check_layout(data: &[u8]) {
    let (text, rest) = match data.iter().position(|&b| b == 0) {
        Some(k) => (&data[..k], &data[k + 1..]),
        None => (data, &[][..]),
    };
    let Ok(text) = std::str::from_utf8(text) else {
        return;
    };
    let spec: LayoutSpec = match text.parse() {
        Ok(s) => s,
        Err(e) => {
            one_line(&format!("{e}"));
            return;
        }
    };
    let shown = spec.to_string();
    let again: LayoutSpec = shown
        .parse()
        .unwrap_or_else(|e| panic!("`{shown}` (from `{text}`) does not parse back: {e}"));
    assert_eq!(again, spec, "`{text}` → `{shown}` changes the spec");
    let mut r = Bytes(rest);
    let mut extent = [0.0f64; 3];
    for e in &mut extent {
        // Zero, tiny, ordinary and huge extents.
        let m = r.u8();
        *e = match m % 4 {
            0 => 0.0,
            1 => f64::from(r.u8()) * 1e-30,
            2 => f64::from(r.u8()) + 1.0,
            _ => f64::from(r.u8()) * 1e30,
        };
    }
    let l = spec.resolve(extent);
    check_layout_shape(&l);
    let _ = format!("{l} {} {}", l.counts_line(), l.pattern_str());
    let rebuilt = Layout::from_channels(l.channels(), l.transform())
        .unwrap_or_else(|e| panic!("{l} does not rebuild from its channels: {e}"));
    assert_eq!(rebuilt.channels(), l.channels());
}

fn check_layout_shape(l: &Layout) {
    assert!(
        l.len() as usize == l.channels().len() && l.len() <= 64,
        "{l}: bad length"
    );
    let counts = l.bit_counts();
    let masks = l.masks();
    let mut all = 0u64;
    for c in 0..4 {
        assert_eq!(masks[c].count_ones(), counts[c], "{l}: mask {c} vs count");
        assert_eq!(all & masks[c], 0, "{l}: masks overlap");
        all |= masks[c];
    }
    assert_eq!(all.count_ones(), l.len(), "{l}: masks vs length");
}

/// A box from six raw `f32` bit patterns (may be NaN, infinite, inverted).
fn raw_box(r: &mut Bytes) -> Aabb {
    let mut v = [0.0f32; 6];
    for x in &mut v {
        // Mostly small integers and fractions, sometimes any bit pattern.
        let tag = r.u8();
        *x = if tag < 200 {
            f32::from(r.u8() as i8) / f32::from(tag % 16 + 1)
        } else {
            f32::from_bits(r.u32())
        };
    }
    Aabb::new(Vec3::new(v[0], v[1], v[2]), Vec3::new(v[3], v[4], v[5]))
}

/// Encoder: a random pattern of 1 to 64 positions (linear or sqrt size) and random boxes; every
/// backend's code equals the reference, batch equals scalar (64- and 32-bit), decode inverts.
pub fn check_encoder(data: &[u8]) {
    let mut r = Bytes(data);
    let head = r.u8();
    let len = usize::from(head % 64) + 1;
    let transform = if head & 0x40 != 0 {
        SizeTransform::Linear
    } else {
        SizeTransform::Sqrt
    };
    let chans: Vec<Channel> = (0..len)
        .map(|_| Channel::ALL[usize::from(r.u8() % 4)])
        .collect();
    let layout = match Layout::from_channels(&chans, transform) {
        Ok(l) => l,
        Err(e) => return one_line(&e.to_string()),
    };
    check_layout_shape(&layout);
    let n = usize::from(r.u8() % 24) + 1;
    let frame_boxes: Vec<Aabb> = (0..n).map(|_| raw_box(&mut r)).collect();
    let frame = match Frame::new(&frame_boxes) {
        Ok(f) => f,
        Err(e) => return one_line(&e.to_string()),
    };
    // Boxes to encode: the frame's own plus any others (outside the frame, or non-finite).
    let mut boxes = frame_boxes;
    while !r.is_empty() && boxes.len() < 64 {
        boxes.push(raw_box(&mut r));
    }
    let reference = Encoder::with_backend(layout, &frame, Backend::Reference)
        .expect("the reference backend always exists");
    let want: Vec<u64> = boxes.iter().map(|b| reference.encode(b)).collect();
    for (b, &c) in boxes.iter().zip(&want) {
        assert_eq!(
            c & !layout.masks().iter().fold(0, |a, m| a | m),
            0,
            "{b:?}: bits outside the layout"
        );
        assert_eq!(
            reference.expand(reference.decode(c)),
            c,
            "decode does not invert"
        );
    }
    for backend in Backend::ALL {
        let Ok(enc) = Encoder::with_backend(layout, &frame, backend) else {
            continue;
        };
        for (b, &c) in boxes.iter().zip(&want) {
            assert_eq!(enc.encode(b), c, "{backend:?} {layout} {b:?}");
            assert_eq!(enc.decode(c), reference.decode(c), "{backend:?} decode");
        }
        let mut batch = vec![0u64; boxes.len()];
        enc.encode_batch(&boxes, &mut batch).expect("same lengths");
        assert_eq!(batch, want, "{backend:?} {layout}: batch vs scalar");
        if layout.fits_u32() {
            let mut b32 = vec![0u32; boxes.len()];
            enc.encode_batch_u32(&boxes, &mut b32).expect("fits u32");
            let w32: Vec<u32> = want.iter().map(|&c| c as u32).collect();
            assert_eq!(b32, w32, "{backend:?} {layout}: u32 batch vs scalar");
        }
    }
}

/// Build + trace: a tiny mesh (up to 12 vertices on a small grid at a chosen scale, up to 16
/// triangles), every builder on a chosen layout and leaf size; the BVH validates, its SAH is
/// finite, and closest and any hit equal brute force on rays through vertices, edges and
/// along axes.
pub fn check_build_trace(data: &[u8]) {
    let mut r = Bytes(data);
    let head = r.u8();
    let scale = [1.0f32, 1e-3, 1e-30, 1e30, 1e-40, 3e5][usize::from(head % 6)];
    let offset = if head & 0x80 != 0 { 1e7f32 } else { 0.0 };
    let nv = usize::from(r.u8() % 12) + 1;
    let vertices: Vec<Vec3> = (0..nv)
        .map(|_| {
            let mut p = [0.0f32; 3];
            for x in &mut p {
                *x = f32::from(r.u8() as i8 % 8) * scale + offset;
            }
            Vec3::from(p)
        })
        .collect();
    let nt = usize::from(r.u8() % 16) + 1;
    let indices: Vec<[u32; 3]> = (0..nt)
        .map(|_| [0; 3].map(|_: u32| u32::from(r.u8()) % nv as u32))
        .collect();
    let scene = Mesh {
        name: "fuzz".into(),
        vertices,
        indices,
        dropped_nonfinite: 0,
    };
    let layout = LayoutSpec::STANDARD[usize::from(r.u8()) % LayoutSpec::STANDARD.len()];
    let max_leaf = u32::from(r.u8() % 8) + 1;
    let tris: Vec<[Vec3; 3]> = (0..nt).map(|i| scene.triangle(i)).collect();
    let rays = fuzz_rays(&tris, &mut r);
    let want: Vec<_> = rays
        .iter()
        .map(|ray| {
            (
                brute_force_closest(ray, &tris),
                brute_force_occluded(ray, &tris),
            )
        })
        .collect();
    for builder in Builder::ALL {
        let opts = PipelineOptions {
            layout: layout.into(),
            builder,
            threads: 1,
            collapse: CollapseParams {
                max_leaf,
                ..CollapseParams::default()
            },
        };
        let label = format!("{builder}/{layout}/leaf {max_leaf}");
        let out = build_scene(&scene, &opts).unwrap_or_else(|e| panic!("{label}: {e}"));
        out.bvh
            .validate(&out.aabbs)
            .unwrap_or_else(|e| panic!("{label}: invalid BVH: {e}"));
        assert!(
            out.report.sah_headline.is_finite() && out.report.sah_collapsed.is_finite(),
            "{label}: SAH not finite"
        );
        let accel = Accel::from_bvh2(&out.bvh, tris.clone())
            .unwrap_or_else(|e| panic!("{label}: conversion: {e}"));
        for (ray, (hit, occ)) in rays.iter().zip(&want) {
            let got = accel.intersect(ray);
            let same = match (hit, got) {
                (None, None) => true,
                (Some(a), Some(b)) => a.t.to_bits() == b.t.to_bits() && a.prim == b.prim,
                _ => false,
            };
            assert!(same, "{label}: {ray:?}: want {hit:?} got {got:?}");
            assert_eq!(accel.occluded(ray), *occ, "{label}: {ray:?} any hit");
        }
    }
}

/// Rays decoded from the rest of the input: origins at vertices, edge points or grid points;
/// directions towards vertices or edge points, along an axis, or in the triangle's plane.
fn fuzz_rays(tris: &[[Vec3; 3]], r: &mut Bytes) -> Vec<Ray> {
    let mut out = Vec::new();
    let (lo, hi) = tris.iter().flatten().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(-f32::MAX)),
        |(lo, hi), &v| (lo.min(v), hi.max(v)),
    );
    let pick = |r: &mut Bytes| {
        let t = tris[usize::from(r.u8()) % tris.len()];
        let (a, b) = (t[usize::from(r.u8()) % 3], t[usize::from(r.u8()) % 3]);
        let s = f32::from(r.u8() % 5) * 0.25;
        a + (b - a) * s
    };
    while !r.is_empty() && out.len() < 32 {
        let kind = r.u8();
        let o = match kind % 3 {
            0 => pick(r),
            _ => {
                let mut u = [0.0f32; 3];
                for x in &mut u {
                    *x = f32::from(r.u8() % 9) * 0.25 - 0.5;
                }
                lo + (hi - lo) * Vec3::from(u)
            }
        };
        let d = match (kind / 3) % 3 {
            0 => pick(r) - o,
            1 => {
                let mut d = Vec3::ZERO;
                d[usize::from(r.u8()) % 3] = if r.u8() & 1 == 0 { 1.0 } else { -1.0 };
                d
            }
            _ => {
                let t = tris[usize::from(r.u8()) % tris.len()];
                t[1] - t[0]
            }
        };
        out.push(Ray::new(o, d));
    }
    out
}
