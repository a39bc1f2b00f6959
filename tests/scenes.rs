//! Mesh loading and built-in scenes: the OBJ front end's errors (file and line), its
//! acceptance rules, zstd round trips, the advertised properties of every `builtin:` scene,
//! and the AVX2 triangle-box path against the scalar reference.

use std::collections::HashMap;
use std::path::PathBuf;

use emc_core::Aabb;
use emc_cpu::aabbs::{chunk_aabbs, triangle_aabbs_with, AabbPath};
use emc_cpu::scene::{self, builtin, obj, Mesh, SceneError, SceneOptions};
use glam::Vec3;

/// A fresh file `name` with `text` in a per-process temporary directory.
fn tmp_file(name: &str, text: &[u8]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("emc-scenes-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn load_text(name: &str, text: &str) -> (PathBuf, Result<Mesh, SceneError>) {
    let p = tmp_file(name, text.as_bytes());
    let r = scene::load(p.to_str().unwrap());
    (p, r)
}

const TRI3: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";

#[test]
fn malformed_lines_name_file_and_line() {
    // (text, line of the error, words the message must contain)
    let cases: &[(&str, usize, &str)] = &[
        ("v 1 2\n", 1, "expected 3 coordinates"),
        ("v 0 0 0\nv 1 x 0\n", 2, "`x` is not a number"),
        ("v 0 0 0\nv 1 0 0 0 0\n", 2, "found 5 numbers"),
        ("v 0 0 0\nv 1 1 1 0\n", 2, "w = 0"),
        ("v 1.0.0 0 0\n", 1, "not a number"),
        ("v 1e 0 0\n", 1, "not a number"),
        ("# c\nvn 1 2\n", 2, "expected 3 numbers"),
        ("vt x 0\n", 1, "not a number"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "index 4"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", 4, "index 0"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", 4, "index -4"),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",
            4,
            "at least 3 vertices",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 c\n",
            4,
            "not a valid index",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1/1/1 2 3\n",
            4,
            "three `/` parts",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf /1 2 3\n",
            4,
            "no vertex index",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/2 2/1 3/1\n",
            5,
            "texture coordinate index 2",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1//1 2//1 3//1\n",
            4,
            "normal index 1",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 99999999999999999999999 1 2\n",
            4,
            "not a valid index",
        ),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1\n", 4, "at least 2 vertices"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl\n", 4, "usemtl"),
        (
            "v 0 0 0\nv 1 0 0 1 1 1\n",
            2,
            "colours must be on every vertex",
        ),
        (
            "v 0 0 0 1 1 1\nv 1 0 0 1 1 1\nv 0 1 0\n",
            3,
            "colours must be on every vertex",
        ),
        // A face may only use vertices defined before it.
        (
            "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
            1,
            "0 defined so far",
        ),
        // Windows line ends count lines the same way.
        (
            "v 0 0 0\r\nv 1 0 0\r\nv 0 1\r\nf 1 2 3\r\n",
            3,
            "expected 3 coordinates",
        ),
    ];
    for (k, &(text, line, words)) in cases.iter().enumerate() {
        let (p, r) = load_text(&format!("bad{k}.obj"), text);
        match r {
            Err(SceneError::Malformed {
                ref path,
                line: l,
                ref message,
            }) => {
                assert_eq!(path, &p, "case {k}");
                assert_eq!(l, line, "case {k}: {message}");
                assert!(
                    message.contains(words),
                    "case {k}: `{message}` lacks `{words}`"
                );
                let shown = r.as_ref().unwrap_err().to_string();
                assert!(
                    shown.starts_with(&format!("{}:{line}: ", p.display())),
                    "case {k}: {shown}"
                );
            }
            other => panic!("case {k} ({text:?}): expected a malformed-line error, got {other:?}"),
        }
    }
}

#[test]
fn invalid_utf8_names_its_line() {
    let p = tmp_file("utf8.obj", b"v 0 0 0\nv 1 0 0\nv 0 \xff 0\nf 1 2 3\n");
    match scene::load(p.to_str().unwrap()) {
        Err(SceneError::Malformed { line, message, .. }) => {
            assert_eq!(line, 3);
            assert!(message.contains("UTF-8"));
        }
        other => panic!("expected malformed, got {other:?}"),
    }
}

#[test]
fn missing_file_is_named() {
    let p = std::env::temp_dir().join("emc-no-such-dir-xyz/nothing.obj");
    let e = scene::load(p.to_str().unwrap()).unwrap_err();
    assert!(matches!(e, SceneError::Open { .. }), "{e:?}");
    assert!(e.to_string().contains("nothing.obj"), "{e}");
    let p = std::env::temp_dir().join("emc-no-such-dir-xyz/nothing.obj.zst");
    let e = scene::load(p.to_str().unwrap()).unwrap_err();
    assert!(matches!(e, SceneError::Open { .. }), "{e:?}");
    let e = scene::load("no-such-shared-scene-name").unwrap_err();
    assert!(matches!(e, SceneError::UnknownScene { .. }), "{e:?}");
}

#[test]
fn empty_and_triangle_free_files_are_errors() {
    for (k, text) in [
        "",
        "\n\n",
        "# only a comment\n",
        TRI3,
        "v 0 0 0\no thing\ng group\n",
    ]
    .iter()
    .enumerate()
    {
        let (p, r) = load_text(&format!("empty{k}.obj"), text);
        match r {
            Err(SceneError::NoTriangles { path }) => assert_eq!(path, p),
            other => panic!("case {k}: expected NoTriangles, got {other:?}"),
        }
    }
}

#[test]
fn nonfinite_triangles_are_dropped_and_counted() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 0\nv 0 inf 0\nv 0 0 -Infinity\n\
                f 1 2 3\nf 1 2 4\nf 5 2 3\nf 6 1 2\nf 3 2 1\n";
    let (_, r) = load_text("nonfinite.obj", text);
    let s = r.unwrap();
    assert_eq!(s.dropped_nonfinite, 3);
    assert_eq!(s.triangle_count(), 2);
    for i in 0..s.triangle_count() {
        assert!(s.triangle(i).iter().all(|v| v.is_finite()));
    }
    assert_eq!(
        s.triangle(1),
        [
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::ZERO
        ]
    );
    // None left: an error that says how many were dropped.
    let (_, r) = load_text(
        "allnan.obj",
        "v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 3 2 1\n",
    );
    match r {
        Err(SceneError::AllNonFinite { dropped, .. }) => assert_eq!(dropped, 2),
        other => panic!("expected AllNonFinite, got {other:?}"),
    }
}

#[test]
fn zero_area_triangles_are_kept() {
    let text = "v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\nf 1 1 2\nf 2 2 2\n";
    let (_, r) = load_text("zeroarea.obj", text);
    let s = r.unwrap();
    assert_eq!(s.triangle_count(), 3);
    assert_eq!(s.dropped_nonfinite, 0);
    assert_eq!(s.triangle(2), [Vec3::ONE; 3]);
}

#[test]
fn polygons_relative_indices_groups_and_extras() {
    // A quad, a pentagon, relative indices, v/vt/vn references, the w vertex form,
    // an mtllib naming a missing file (ignored), objects and groups, points and lines.
    let text = "mtllib missing.mtl\n# comment\no first\n\
                v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
                vt 0 0\nvn 0 0 1\n\
                f 1/1/1 2/1/1 3//1 4/1\n\
                g second\nusemtl nothing\n\
                v 0 0 5\nv 2 0 5 1\nv 2 2 10 2\nv 0 2 5\nv 0 1 5\n\
                f -5 -4 -3 -2 -1\n\
                p 1\nl 1 2\n\
                s off\nf -1 -2 -3\n";
    let (_, r) = load_text("poly.obj", text);
    let s = r.unwrap();
    assert_eq!(s.triangle_count(), 2 + 3 + 1);
    assert_eq!(s.name, "poly");
    let all: Vec<[Vec3; 3]> = (0..s.triangle_count()).map(|i| s.triangle(i)).collect();
    // The quad is fanned from its first vertex.
    assert_eq!(all[0], [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0)]);
    assert_eq!(all[1], [Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0), Vec3::Y]);
    // w divides: (2, 2, 10) / 2 = (1, 1, 5).
    let p = [
        Vec3::new(0.0, 0.0, 5.0),
        Vec3::new(2.0, 0.0, 5.0),
        Vec3::new(1.0, 1.0, 5.0),
        Vec3::new(0.0, 2.0, 5.0),
        Vec3::new(0.0, 1.0, 5.0),
    ];
    assert_eq!(all[2], [p[0], p[1], p[2]]);
    assert_eq!(all[3], [p[0], p[2], p[3]]);
    assert_eq!(all[4], [p[0], p[3], p[4]]);
    assert_eq!(all[5], [p[4], p[3], p[2]]);
    assert!(s
        .indices
        .iter()
        .flatten()
        .all(|&i| (i as usize) < s.vertices.len()));
}

#[test]
fn coloured_vertices_load() {
    let text = "v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n";
    let (_, r) = load_text("rgb.obj", text);
    let s = r.unwrap();
    assert_eq!(s.triangle(0), [Vec3::ZERO, Vec3::X, Vec3::Y]);
}

#[test]
fn zst_round_trip_and_plain_round_trip() {
    for (name, prims) in [
        ("sphere", Some(1280)),
        ("city", Some(5000)),
        ("mixed", Some(3000)),
    ] {
        let opts = SceneOptions::default().with_prims(prims).with_seed(7);
        let s = scene::load_with(&format!("builtin:{name}"), &opts).unwrap();
        for ext in ["obj", "obj.zst"] {
            let p = tmp_file(&format!("rt-{name}.{ext}"), b"");
            obj::save_obj(&s, &p).unwrap();
            let back = scene::load(p.to_str().unwrap()).unwrap();
            assert_eq!(back.name, format!("rt-{name}"));
            assert_eq!(back.triangle_count(), s.triangle_count(), "{name}.{ext}");
            for i in 0..s.triangle_count() {
                assert_eq!(back.triangle(i), s.triangle(i), "{name}.{ext} triangle {i}");
            }
        }
    }
    // A damaged zstd stream is a read error naming the file.
    let p = tmp_file("broken.obj.zst", b"\x28\xb5\x2f\xfd garbage");
    let e = scene::load(p.to_str().unwrap()).unwrap_err();
    assert!(matches!(e, SceneError::Read { .. }), "{e:?}");
    assert!(e.to_string().contains("broken.obj.zst"));
}

fn gen(name: &str, prims: Option<usize>, seed: u64) -> Mesh {
    scene::load_with(
        &format!("builtin:{name}"),
        &SceneOptions::default().with_prims(prims).with_seed(seed),
    )
    .unwrap()
}

fn bit_eq(a: &Mesh, b: &Mesh) -> bool {
    let bits = |s: &Mesh| -> Vec<u32> {
        s.vertices
            .iter()
            .flat_map(|v| v.to_array().map(f32::to_bits))
            .collect()
    };
    a.indices == b.indices && bits(a) == bits(b)
}

#[test]
fn builtins_are_deterministic_and_sized_as_documented() {
    for name in builtin::NAMES {
        let a = gen(name, Some(3000), 1);
        let b = gen(name, Some(3000), 1);
        assert!(bit_eq(&a, &b), "{name} not deterministic");
        let c = gen(name, Some(3000), 2);
        if name == "sphere" {
            assert!(bit_eq(&a, &c), "sphere ignores the seed");
        } else {
            assert!(!bit_eq(&a, &c), "{name}: seed has no effect");
        }
        assert!(a.vertices.iter().all(|v| v.is_finite()), "{name}");
        assert!(a
            .indices
            .iter()
            .flatten()
            .all(|&i| (i as usize) < a.vertices.len()));
        assert_eq!(a.name, format!("builtin:{name}"));
        for n in [1usize, 2, 63, 64, 1000, 12_345] {
            let s = gen(name, Some(n), 3);
            let expected = match name {
                "stadium" | "city" => n.max(64),
                "sphere" => 20 << (2 * builtin::sphere_level(Some(n))),
                _ => n,
            };
            assert_eq!(s.triangle_count(), expected, "{name} prims {n}");
        }
        let e = scene::load_with(
            &format!("builtin:{name}"),
            &SceneOptions::default().with_prims(0).with_seed(0),
        )
        .unwrap_err();
        assert!(matches!(e, SceneError::ZeroPrims(_)), "{e:?}");
    }
    assert_eq!(builtin::sphere_level(None), 7);
    assert_eq!(builtin::sphere_level(Some(1)), 0);
    assert_eq!(builtin::sphere_level(Some(20_000)), 5); // 20,480
    assert!(matches!(
        scene::load("builtin:nope"),
        Err(SceneError::UnknownBuiltin(_))
    ));
}

#[test]
fn builtin_default_sizes() {
    for name in builtin::NAMES {
        let s = scene::load(&format!("builtin:{name}")).unwrap();
        let expected = if name == "sphere" {
            327_680
        } else {
            builtin::DEFAULT_PRIMS
        };
        assert_eq!(s.triangle_count(), expected, "{name}");
    }
}

fn diag(b: &Aabb) -> f32 {
    (b.max - b.min).length()
}

#[test]
fn city_is_flat_and_has_very_different_buildings() {
    let s = gen("city", Some(50_000), 11);
    let b = s.bounds();
    let e = b.max - b.min;
    assert!(e.x / e.z >= 100.0, "extent {e:?}");
    assert!(e.x.max(e.y) / e.x.min(e.y).min(e.z) >= 100.0);
    // The centroid box (what codes are normalised to) is as flat.
    let boxes = s.aabbs();
    let sb = s.scene_bounds(&boxes).unwrap();
    let ce: Vec<f64> = (0..3)
        .map(|a| sb.centroid_max[a] - sb.centroid_min[a])
        .collect();
    assert!(ce[0] / ce[2] >= 100.0, "centroid extent {ce:?}");
    // Building heights differ by more than 10x (walls are split per floor, so look at the
    // tallest vertex of the scene against the typical small building: the median roof).
    let mut d: Vec<f32> = boxes.iter().map(diag).collect();
    d.sort_by(f32::total_cmp);
    assert!(
        d[d.len() - 1] / d[d.len() / 2] > 1000.0,
        "ground vs median triangle"
    );
    let tallest = b.max.z;
    assert!(
        tallest > 100.0 && tallest <= builtin::CITY_MAX_HEIGHT,
        "{tallest}"
    );
}

#[test]
fn stadium_has_a_huge_sparse_ground_and_a_tiny_dense_object() {
    let s = gen("stadium", Some(100_000), 5);
    let boxes = s.aabbs();
    let b = s.bounds();
    // Most triangles sit in a ball of radius 1 that is 1/1000 of the scene's width.
    let near = boxes.iter().filter(|x| x.max.length() < 4.0).count();
    assert!(near * 10 >= s.triangle_count() * 9, "{near}");
    assert!((b.max.x - b.min.x) >= 999.0);
    let mut d: Vec<f32> = boxes.iter().map(diag).collect();
    d.sort_by(f32::total_cmp);
    assert!(d[d.len() - 1] / d[d.len() / 2] > 1000.0);
}

#[test]
fn hair_is_long_thin_triangles() {
    let s = gen("hair", Some(20_000), 5);
    let mut aspect: Vec<f32> = (0..s.triangle_count())
        .map(|i| {
            let [a, b, c] = s.triangle(i);
            let longest = (b - a).length().max((c - b).length()).max((a - c).length());
            let area2 = (b - a).cross(c - a).length();
            longest * longest / area2.max(f32::MIN_POSITIVE)
        })
        .collect();
    aspect.sort_by(f32::total_cmp);
    // longest edge over its height: a 0.06 x 0.002 ribbon half has about 30.
    assert!(
        aspect[aspect.len() / 2] > 20.0,
        "median aspect {}",
        aspect[aspect.len() / 2]
    );
}

#[test]
fn mixed_has_huge_and_tiny_primitives_in_one_place() {
    let s = gen("mixed", Some(20_000), 5);
    let boxes = s.aabbs();
    let mut d: Vec<f32> = boxes.iter().map(diag).collect();
    d.sort_by(f32::total_cmp);
    assert!(d[d.len() - 1] / d[0] > 1e4, "{} / {}", d[d.len() - 1], d[0]);
    // Big and small share the same region: the big ones' centres and the small ones' centres
    // both spread over the whole cube.
    let big: Vec<&Aabb> = boxes.iter().filter(|b| diag(b) > 3.0).collect();
    assert!(big.len() >= 100 && big.len() < 400, "{}", big.len());
    let small = Aabb::EMPTY;
    let small = boxes
        .iter()
        .filter(|b| diag(b) < 0.2)
        .fold(small, |a, b| a.union(b));
    assert!(small.max.min_element() > 9.0 && small.min.max_element() < 1.0);
}

#[test]
fn sphere_is_watertight_and_round() {
    for level in [0u32, 1, 3] {
        let s = builtin::icosphere(level, 1.0);
        let f = s.triangle_count();
        assert_eq!(f, 20 << (2 * level));
        // Euler characteristic of a sphere, every undirected edge in exactly two triangles,
        // every directed edge in exactly one (consistent orientation).
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &s.indices {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        assert!(directed.values().all(|&c| c == 1), "level {level}");
        assert!(directed
            .keys()
            .all(|&(a, b)| directed.contains_key(&(b, a))));
        let e = directed.len() / 2;
        assert_eq!(s.vertices.len() as i64 - e as i64 + f as i64, 2);
        assert!(s.vertices.iter().all(|v| (v.length() - 1.0).abs() < 1e-6));
        // Outward orientation: the normal points away from the centre.
        for i in 0..f {
            let [a, b, c] = s.triangle(i);
            assert!(
                (b - a).cross(c - a).dot(a + b + c) > 0.0,
                "level {level} tri {i}"
            );
        }
    }
}

fn box_bits(b: &[Aabb]) -> Vec<u32> {
    b.iter()
        .flat_map(|x| [x.min, x.max])
        .flat_map(|v| v.to_array().map(f32::to_bits))
        .collect()
}

#[test]
fn simd_boxes_equal_scalar_on_every_builtin() {
    println!("AABB path: {}", AabbPath::detect().describe());
    for name in builtin::NAMES {
        let s = gen(name, Some(40_000), 9);
        let n = s.triangle_count();
        let mut scalar = vec![Aabb::EMPTY; n];
        triangle_aabbs_with(AabbPath::Scalar, &s.vertices, &s.indices, &mut scalar);
        let best = s.aabbs();
        assert_eq!(box_bits(&best), box_bits(&scalar), "{name}");
        // The scalar path is the plain triangle box.
        for (i, b) in scalar.iter().enumerate() {
            let [p, q, r] = s.triangle(i);
            assert_eq!(*b, Aabb::from_triangle(p, q, r), "{name} {i}");
        }
    }
}

#[test]
fn simd_boxes_equal_scalar_on_odd_indices_and_signed_zeros() {
    // Indices hitting the last vertex (whose 16-byte load would overrun), repeated indices,
    // every slice length up to 40, signed zeros, subnormals and NaN vertices.
    let mut rng = builtin::Pcg32::new(42, 1);
    let specials = [
        0.0f32,
        -0.0,
        f32::MIN_POSITIVE / 4.0,
        -f32::MIN_POSITIVE,
        f32::MAX,
        f32::MIN,
        f32::NAN,
        f32::INFINITY,
        1.0,
    ];
    let vertices: Vec<Vec3> = (0..64)
        .map(|_| {
            let mut c = || specials[(rng.next_u32() % specials.len() as u32) as usize];
            Vec3::new(c(), c(), c())
        })
        .collect();
    let nv = vertices.len() as u32;
    for len in 0..40usize {
        let indices: Vec<[u32; 3]> = (0..len)
            .map(|k| {
                if k % 3 == 0 {
                    [nv - 1, nv - 1, rng.next_u32() % nv]
                } else {
                    [
                        rng.next_u32() % nv,
                        rng.next_u32() % nv,
                        rng.next_u32() % nv,
                    ]
                }
            })
            .collect();
        let mut a = vec![Aabb::EMPTY; len];
        let mut b = vec![Aabb::EMPTY; len];
        chunk_aabbs(AabbPath::Scalar, &vertices, &indices, &mut a);
        chunk_aabbs(AabbPath::detect(), &vertices, &indices, &mut b);
        assert_eq!(box_bits(&a), box_bits(&b), "len {len}");
    }
}

#[test]
fn shared_scenes_resolve_by_name() {
    let Some(dir) = scene::shared_scenes_dir() else {
        println!("skipped: no shared scenes directory (set EMC_SHARED_DIR)");
        return;
    };
    let mut any = false;
    for (name, tris) in scene::SHARED_SCENES {
        if tris > 1_000_000 {
            continue;
        }
        let Some(p) = scene::shared_scene_path(name) else {
            println!("skipped {name}: not in {}", dir.display());
            continue;
        };
        any = true;
        let s = scene::load(name).unwrap();
        assert_eq!(s.triangle_count(), tris, "{name} ({})", p.display());
        assert_eq!(s.dropped_nonfinite, 0);
        assert_eq!(s.name, name);
        let mut scalar = vec![Aabb::EMPTY; tris];
        triangle_aabbs_with(AabbPath::Scalar, &s.vertices, &s.indices, &mut scalar);
        assert_eq!(box_bits(&s.aabbs()), box_bits(&scalar), "{name}");
    }
    if !any {
        println!("skipped: no shared scene of at most 1M triangles found");
    }
}

#[test]
fn hard_cases_have_their_shape() {
    let n = 3000;
    for name in builtin::HARD_NAMES {
        let a = gen(name, Some(n), 4);
        let b = gen(name, Some(n), 4);
        assert!(bit_eq(&a, &b), "{name} not deterministic");
        assert_eq!(a.name, format!("builtin:{name}"));
        if name != "hard-nonfinite" {
            assert_eq!(a.triangle_count(), n, "{name}");
            assert_eq!(a.dropped_nonfinite, 0, "{name}");
        }
        assert!(a
            .indices
            .iter()
            .flatten()
            .all(|&i| (i as usize) < a.vertices.len()));
        for i in 0..a.triangle_count() {
            assert!(a.triangle(i).iter().all(|v| v.is_finite()), "{name} {i}");
        }
        let v = &a.vertices;
        let bounds = a.bounds();
        let e = bounds.max - bounds.min;
        match name {
            "hard-point" => assert!(v.iter().all(|&p| p == v[0])),
            "hard-plane-x" => assert!(v.iter().all(|p| p.x == 5.0) && e.y > 50.0),
            "hard-plane-y" => assert!(v.iter().all(|p| p.y == 5.0) && e.z > 50.0),
            "hard-plane-z" => assert!(v.iter().all(|p| p.z == 5.0) && e.x > 50.0),
            "hard-far" => {
                assert!(bounds.min.min_element() >= 1e7 - 1.0 && e.max_element() <= 101.0)
            }
            "hard-huge" => {
                assert!(e.x > f32::MAX / 2.0 && e.is_finite());
                // The f32 area overflows; the f64 one does not.
                let big = a.aabbs().iter().map(|b| b.area_f64()).fold(0.0, f64::max);
                assert!(big.is_finite() && big > f32::MAX as f64);
            }
            "hard-tiny" => assert!(v.iter().all(|p| p
                .to_array()
                .iter()
                .all(|&c| (f32::MIN_POSITIVE..16.0 * f32::MIN_POSITIVE).contains(&c)))),
            "hard-subnormal" => {
                assert!(v.iter().all(|p| p
                    .to_array()
                    .iter()
                    .all(|&c| (0.0..f32::MIN_POSITIVE).contains(&c))));
                assert!(e.min_element() > 0.0 && e.max_element() < f32::MIN_POSITIVE);
            }
            "hard-needles" => {
                let zero = (0..n)
                    .filter(|&i| {
                        let [p, q, r] = a.triangle(i);
                        (q - p).cross(r - p) == Vec3::ZERO
                    })
                    .count();
                assert!(zero >= n / 3, "{zero}");
            }
            "hard-one-big" => {
                let boxes = a.aabbs();
                assert!(boxes.iter().all(|b| boxes[0].contains(b)));
                assert!(boxes[1..].iter().all(|b| diag(b) < 2e-3));
                assert_eq!(
                    scene::load("builtin:hard-one-big")
                        .unwrap()
                        .triangle_count(),
                    1_000_001
                );
            }
            "hard-same-cell" => {
                let inner = a.aabbs()[2..].iter().fold(Aabb::EMPTY, |x, b| x.union(b));
                let ie = inner.max - inner.min;
                assert!(ie.max_element() <= 1.0 / (1u32 << 22) as f32, "{ie:?}");
                assert!(e.min_element() >= 1.0);
            }
            "hard-elongated" => assert!(e.x / e.y.max(e.z) >= 1e5 * 0.98, "{e:?}"),
            "hard-nonfinite" => {
                assert!(a.dropped_nonfinite > 0);
                assert_eq!(a.triangle_count() + a.dropped_nonfinite, n);
                assert!(a.vertices.iter().any(|p| !p.is_finite()));
            }
            "hard-duplicates" => assert!((0..n).all(|i| a.triangle(i) == a.triangle(0))),
            _ => unreachable!("{name}"),
        }
        // The AVX2 boxes equal the scalar boxes here too.
        let mut scalar = vec![Aabb::EMPTY; a.triangle_count()];
        triangle_aabbs_with(AabbPath::Scalar, &a.vertices, &a.indices, &mut scalar);
        assert_eq!(box_bits(&a.aabbs()), box_bits(&scalar), "{name}");
    }
    assert_eq!(
        scene::load("builtin:hard-same-cell")
            .unwrap()
            .triangle_count(),
        (1 << 21) + 3
    );
}

/// `builtin:wave`: the same indices at every frame, the same vertices for the same frame, moved
/// vertices for another, `2(n − 1)²` triangles for the grid side of `--prims`, and every
/// vertex finite and named by a triangle.
#[test]
fn wave_frames_are_deterministic_and_share_their_mesh() {
    let at = |frame| {
        scene::load_with(
            "builtin:wave",
            &SceneOptions::default().with_prims(5000).with_frame(frame),
        )
        .unwrap()
    };
    let (a, b, c) = (at(7), at(7), at(8));
    assert_eq!(a.vertices, b.vertices);
    assert_eq!(a.indices, c.indices);
    assert_ne!(a.vertices, c.vertices);
    let side = emc_cpu::scene::builtin::wave_side(5000);
    assert_eq!(a.triangle_count(), 2 * (side - 1) * (side - 1));
    assert!(a.vertices.iter().all(|v| v.is_finite()));
    let mut named = vec![false; a.vertices.len()];
    for t in &a.indices {
        for &i in t {
            named[i as usize] = true;
        }
    }
    assert!(named.iter().all(|&n| n));
    // The twist grows: frame 48 spans more of z than frame 0.
    let zspan = |s: &emc_cpu::Mesh| {
        let (lo, hi) = s
            .vertices
            .iter()
            .fold((f32::MAX, f32::MIN), |(l, h), v| (l.min(v.z), h.max(v.z)));
        hi - lo
    };
    assert!(zspan(&at(48)) > 2.0 * zspan(&at(0)));
}
