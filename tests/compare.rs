//! Tests of `emc compare` and the in-process peers (`emc_cpu::peers`). Without the `peers`
//! feature: the verb measures emc alone and says the peers need the feature. With it
//! (`cargo test --release -p emc-tests --features peers --test compare`): the Embree binding's
//! struct layouts equal the C compiler's view of the headers, Embree in process answers every
//! ray exactly as the peer harness (`../shared/peers`) does on a small built-in scene, and
//! Embree's, obvhs' and emc's protocol counts agree within 0.05% on the shared scenes ≤ 1M
//! triangles. Tests that need `../shared` skip with a message when it is absent.

use std::path::PathBuf;

use emc_cpu::cli::compare::{run, CompareArgs, CSV_HEADER};

/// A scratch folder private to this test process and test, removed when dropped.
struct Scratch(PathBuf);

impl Scratch {
    fn new(test: &str) -> Scratch {
        let d = std::env::temp_dir().join(format!("emc-compare-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&d).expect("temp dir");
        Scratch(d)
    }
    fn join(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Rows of a CSV written by `emc compare --csv`, as (header → value) lookups.
fn read_csv(path: &PathBuf) -> Vec<Vec<(String, String)>> {
    read_csv_with(path, CSV_HEADER)
}

fn read_csv_with(path: &PathBuf, want: &str) -> Vec<Vec<(String, String)>> {
    let text = std::fs::read_to_string(path).expect("csv written");
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .expect("header")
        .split(',')
        .map(String::from)
        .collect();
    assert_eq!(header.join(","), want);
    lines
        .map(|l| {
            let cells: Vec<&str> = l.split(',').collect();
            assert_eq!(cells.len(), header.len(), "row {l}");
            header
                .iter()
                .cloned()
                .zip(cells.iter().map(|c| c.to_string()))
                .collect()
        })
        .collect()
}

fn cell<'a>(row: &'a [(String, String)], name: &str) -> &'a str {
    &row.iter().find(|(h, _)| h == name).expect("column").1
}

/// The verb on a small built-in scene, in process, with its CSV read back.
fn compare_small(presets: &str, threads: usize) -> Vec<Vec<(String, String)>> {
    let dir = Scratch::new(&format!("small-{threads}"));
    let csv = dir.join("small.csv");
    run(&CompareArgs {
        scenes: vec!["builtin:city".into()],
        threads,
        csv: Some(csv.to_string_lossy().into_owned()),
        runs: 1,
        presets: presets.into(),
        res: 64,
        camera: None,
        prims: Some(3000),
        frames: None,
        instances: None,
    })
    .expect("emc compare runs");
    read_csv(&csv)
}

/// `--frames` on the animated scene: one CSV row per frame with positive update times and
/// trace speeds for emc, and for Embree's REFIT and LOW commits where the feature is on; a
/// scene that is not animated is refused.
#[test]
fn frames_report_a_row_per_frame() {
    let dir = Scratch::new("frames");
    let csv = dir.join("frames.csv");
    let args = |scene: &str| CompareArgs {
        scenes: vec![scene.into()],
        threads: 1,
        csv: Some(csv.to_string_lossy().into_owned()),
        runs: 1,
        presets: "fast".into(),
        res: 48,
        camera: None,
        prims: Some(4000),
        frames: Some(3),
        instances: None,
    };
    run(&args("builtin:wave")).expect("emc compare --frames runs");
    let rows = read_csv_with(&csv, emc_cpu::cli::frames::FRAMES_CSV_HEADER);
    assert_eq!(rows.len(), 3);
    for (k, r) in rows.iter().enumerate() {
        assert_eq!(cell(r, "frame"), (k + 1).to_string());
        for col in ["refit_ms", "rebuild_ms", "mrays_refit", "mrays_rebuild"] {
            let v: f64 = cell(r, col).parse().unwrap();
            assert!(v > 0.0, "{col} = {v}");
        }
        for col in ["embree_refit_ms", "embree_low_ms", "mrays_embree_refit"] {
            assert_eq!(!cell(r, col).is_empty(), cfg!(feature = "peers"), "{col}");
        }
    }
    let e = run(&args("builtin:city")).unwrap_err().to_string();
    assert!(e.contains("animated"), "{e}");
}

#[test]
fn bad_arguments_are_errors() {
    let base = CompareArgs {
        scenes: vec!["builtin:city".into()],
        threads: 1,
        csv: None,
        runs: 1,
        presets: "fast".into(),
        res: 16,
        camera: None,
        prims: Some(100),
        frames: None,
        instances: None,
    };
    let cases: Vec<(CompareArgs, &str)> = vec![
        (
            CompareArgs {
                threads: 0,
                ..base.clone()
            },
            "--threads",
        ),
        (
            CompareArgs {
                runs: 0,
                ..base.clone()
            },
            "--runs",
        ),
        (
            CompareArgs {
                presets: "fast,turbo".into(),
                ..base.clone()
            },
            "turbo",
        ),
        (
            CompareArgs {
                presets: ",".into(),
                ..base.clone()
            },
            "no preset",
        ),
        (
            CompareArgs {
                camera: Some("above".into()),
                ..base.clone()
            },
            "above",
        ),
        (
            CompareArgs {
                scenes: vec!["builtin:nothing".into()],
                ..base.clone()
            },
            "nothing",
        ),
        (
            CompareArgs {
                csv: Some("/nonexistent-dir/x.csv".into()),
                ..base.clone()
            },
            "nonexistent-dir",
        ),
        (
            CompareArgs {
                frames: Some(0),
                instances: None,
                scenes: vec!["builtin:wave".into()],
                ..base.clone()
            },
            "--frames",
        ),
    ];
    for (args, word) in cases {
        let e = run(&args).expect_err("must fail");
        let msg = format!("{e:#}");
        assert!(msg.contains(word), "`{word}` missing in: {msg}");
    }
}

/// Without the feature: emc's rows only, and the `emc` binary says the peers need it.
#[cfg(not(feature = "peers"))]
#[test]
fn without_the_feature_emc_rows_and_a_note() {
    let rows = compare_small("fast,quality", 1);
    let configs: Vec<&str> = rows.iter().map(|r| cell(r, "config")).collect();
    assert_eq!(configs, ["emc fast", "emc quality"]);
    for r in &rows {
        assert_eq!(cell(r, "peer"), "0");
        assert_eq!(cell(r, "cold_vs_best_peer"), "", "no peer, no ratio");
        assert!(cell(r, "primary_hits").parse::<u64>().unwrap() > 0);
    }

    // `target/<profile>/emc`, next to the `deps` folder holding this test executable.
    let exe = std::env::current_exe().expect("test exe");
    let emc = exe.parent().and_then(|d| d.parent()).map(|d| d.join("emc"));
    let Some(emc) = emc.filter(|p| p.is_file()) else {
        eprintln!("the emc binary is not built next to this test; CLI message not checked");
        return;
    };
    let out = std::process::Command::new(emc)
        .args(["compare", "builtin:city", "--prims", "500", "--res", "16"])
        .args(["--runs", "1", "--presets", "fast"])
        .output()
        .expect("emc runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("need `--features peers`"), "{stdout}");
    assert!(stdout.contains("emc fast"), "{stdout}");
    assert!(!stdout.contains("embree"), "{stdout}");
}

/// With the feature: every configuration has a row, emc's rows carry ratios to the best peer
/// that are the quotients of the figures in the same file, and 1 and 2 threads count alike.
#[cfg(feature = "peers")]
#[test]
fn with_the_feature_peer_rows_and_ratios() {
    let rows = compare_small("fast,balanced,quality", 1);
    let configs: Vec<&str> = rows.iter().map(|r| cell(r, "config")).collect();
    assert_eq!(
        configs,
        [
            "emc fast",
            "emc balanced",
            "emc quality",
            "embree LOW",
            "embree MEDIUM",
            "obvhs fastest"
        ]
    );
    let num = |r: &[(String, String)], c: &str| cell(r, c).parse::<f64>().unwrap();
    let peers: Vec<_> = rows.iter().filter(|r| cell(r, "peer") == "1").collect();
    let best_cold = peers
        .iter()
        .map(|r| num(r, "build_cold_ms"))
        .fold(f64::INFINITY, f64::min);
    let best_ao = peers.iter().map(|r| num(r, "ao_mrays")).fold(0.0, f64::max);
    let embree_hits = num(peers[0], "primary_hits");
    for r in &rows {
        assert!(num(r, "build_cold_ms") > 0.0 && num(r, "primary_mrays") > 0.0);
        let hits = num(r, "primary_hits");
        assert!(
            (hits - embree_hits).abs() <= 5e-4 * embree_hits,
            "{} hits {hits} vs Embree {embree_hits}",
            cell(r, "config")
        );
        if cell(r, "peer") == "1" {
            assert_eq!(cell(r, "cold_vs_best_peer"), "");
            continue;
        }
        // The file rounds ms to 3 decimals and Mrays/s to 4 (sub-ms builds here): within 1%.
        let cold = num(r, "build_cold_ms") / best_cold;
        let got = num(r, "cold_vs_best_peer");
        assert!(
            (got - cold).abs() <= 1e-2 * cold,
            "cold ratio {got} vs {cold}"
        );
        let ao = num(r, "ao_mrays") / best_ao;
        let got = num(r, "ao_vs_best_peer");
        assert!((got - ao).abs() <= 1e-2 * ao, "AO ratio {got} vs {ao}");
    }
    let two = compare_small("fast", 2);
    for r in &two {
        let one = rows
            .iter()
            .find(|o| cell(o, "config") == cell(r, "config"))
            .unwrap();
        for c in ["primary_hits", "ao_rays", "ao_occluded"] {
            assert_eq!(cell(one, c), cell(r, c), "{} {c}", cell(r, "config"));
        }
    }
}

#[cfg(feature = "peers")]
mod peers {
    use super::*;
    use emc_cpu::peers::embree::{sys, Device, Mesh as EMesh, Quality, Scene as EScene};
    use emc_cpu::peers::obvhs;
    use emc_cpu::peers::{FtzGuard, Protocol, Tracer};
    use emc_cpu::scene::{self, Mesh, SceneOptions};
    use emc_cpu::trace::workload::CameraMode;
    use emc_cpu::trace::{Accel, BuildOptions, Preset};
    use glam::Vec3;
    use std::mem::{align_of, offset_of, size_of};
    use std::process::Command;

    fn triangles(s: &Mesh) -> Vec<[Vec3; 3]> {
        (0..s.triangle_count()).map(|i| s.triangle(i)).collect()
    }

    /// What the C compiler says about the headers: `name value` per line.
    fn c_layout() -> Vec<(String, i64)> {
        let dir = Scratch::new("layout");
        let src = dir.join("layout.c");
        let exe = dir.join("layout");
        let mut c = String::from(
            "#include <embree3/rtcore.h>\n#include <stdio.h>\n#include <stddef.h>\n\
             #define P(n, v) printf(\"%s %lld\\n\", n, (long long)(v))\nint main(void) {\n",
        );
        for (ty, fields) in [
            (
                "RTCRay",
                &[
                    "org_x", "org_y", "org_z", "tnear", "dir_x", "dir_y", "dir_z", "time", "tfar",
                    "mask", "id", "flags",
                ][..],
            ),
            (
                "RTCHit",
                &[
                    "Ng_x", "Ng_y", "Ng_z", "u", "v", "primID", "geomID", "instID",
                ][..],
            ),
            ("RTCRayHit", &["ray", "hit"][..]),
            ("RTCIntersectContext", &["flags", "filter", "instID"][..]),
        ] {
            c += &format!(
                "P(\"{ty}.size\", sizeof(struct {ty}));\nP(\"{ty}.align\", _Alignof(struct {ty}));\n"
            );
            for f in fields {
                c += &format!("P(\"{ty}.{f}\", offsetof(struct {ty}, {f}));\n");
            }
        }
        for (name, expr) in [
            ("enum", "sizeof(enum RTCBuildQuality)"),
            ("LOW", "RTC_BUILD_QUALITY_LOW"),
            ("MEDIUM", "RTC_BUILD_QUALITY_MEDIUM"),
            ("FLOAT3", "RTC_FORMAT_FLOAT3"),
            ("UINT3", "RTC_FORMAT_UINT3"),
            ("VERTEX", "RTC_BUFFER_TYPE_VERTEX"),
            ("INDEX", "RTC_BUFFER_TYPE_INDEX"),
            ("TRIANGLE", "RTC_GEOMETRY_TYPE_TRIANGLE"),
            ("COHERENT", "RTC_INTERSECT_CONTEXT_FLAG_COHERENT"),
            ("INCOHERENT", "RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT"),
            ("NONE", "RTC_SCENE_FLAG_NONE"),
            ("VERSION", "RTC_DEVICE_PROPERTY_VERSION"),
            ("INVALID", "RTC_INVALID_GEOMETRY_ID"),
            ("ssize_t", "sizeof(ssize_t)"),
            ("instances", "RTC_MAX_INSTANCE_LEVEL_COUNT"),
        ] {
            c += &format!("P(\"{name}\", {expr});\n");
        }
        c += "return 0; }\n";
        std::fs::write(&src, c).unwrap();
        let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        let st = Command::new(&cc)
            .arg(&src)
            .arg("-o")
            .arg(&exe)
            .status()
            .unwrap_or_else(|e| panic!("cannot run the C compiler `{cc}`: {e}"));
        assert!(st.success(), "{cc} failed on the Embree headers");
        let out = Command::new(&exe).output().expect("layout program runs");
        String::from_utf8(out.stdout)
            .unwrap()
            .lines()
            .map(|l| {
                let (n, v) = l.split_once(' ').unwrap();
                (n.to_string(), v.parse().unwrap())
            })
            .collect()
    }

    #[test]
    fn struct_layouts_match_the_headers() {
        let c = c_layout();
        let get = |n: &str| {
            c.iter()
                .find(|(k, _)| k == n)
                .unwrap_or_else(|| panic!("{n} not printed"))
                .1
        };
        macro_rules! same {
            ($name:literal, $rust:expr) => {
                assert_eq!(get($name), $rust as i64, "{}", $name);
            };
        }
        same!("RTCRay.size", size_of::<sys::RTCRay>());
        same!("RTCRay.align", align_of::<sys::RTCRay>());
        same!("RTCRay.org_x", offset_of!(sys::RTCRay, org_x));
        same!("RTCRay.org_y", offset_of!(sys::RTCRay, org_y));
        same!("RTCRay.org_z", offset_of!(sys::RTCRay, org_z));
        same!("RTCRay.tnear", offset_of!(sys::RTCRay, tnear));
        same!("RTCRay.dir_x", offset_of!(sys::RTCRay, dir_x));
        same!("RTCRay.dir_y", offset_of!(sys::RTCRay, dir_y));
        same!("RTCRay.dir_z", offset_of!(sys::RTCRay, dir_z));
        same!("RTCRay.time", offset_of!(sys::RTCRay, time));
        same!("RTCRay.tfar", offset_of!(sys::RTCRay, tfar));
        same!("RTCRay.mask", offset_of!(sys::RTCRay, mask));
        same!("RTCRay.id", offset_of!(sys::RTCRay, id));
        same!("RTCRay.flags", offset_of!(sys::RTCRay, flags));
        same!("RTCHit.size", size_of::<sys::RTCHit>());
        same!("RTCHit.align", align_of::<sys::RTCHit>());
        same!("RTCHit.Ng_x", offset_of!(sys::RTCHit, ng_x));
        same!("RTCHit.Ng_y", offset_of!(sys::RTCHit, ng_y));
        same!("RTCHit.Ng_z", offset_of!(sys::RTCHit, ng_z));
        same!("RTCHit.u", offset_of!(sys::RTCHit, u));
        same!("RTCHit.v", offset_of!(sys::RTCHit, v));
        same!("RTCHit.primID", offset_of!(sys::RTCHit, prim_id));
        same!("RTCHit.geomID", offset_of!(sys::RTCHit, geom_id));
        same!("RTCHit.instID", offset_of!(sys::RTCHit, inst_id));
        same!("RTCRayHit.size", size_of::<sys::RTCRayHit>());
        same!("RTCRayHit.align", align_of::<sys::RTCRayHit>());
        same!("RTCRayHit.ray", offset_of!(sys::RTCRayHit, ray));
        same!("RTCRayHit.hit", offset_of!(sys::RTCRayHit, hit));
        same!(
            "RTCIntersectContext.size",
            size_of::<sys::RTCIntersectContext>()
        );
        same!(
            "RTCIntersectContext.align",
            align_of::<sys::RTCIntersectContext>()
        );
        same!(
            "RTCIntersectContext.flags",
            offset_of!(sys::RTCIntersectContext, flags)
        );
        same!(
            "RTCIntersectContext.filter",
            offset_of!(sys::RTCIntersectContext, filter)
        );
        same!(
            "RTCIntersectContext.instID",
            offset_of!(sys::RTCIntersectContext, inst_id)
        );
        same!("enum", size_of::<sys::RTCBuildQuality>());
        same!("LOW", sys::RTC_BUILD_QUALITY_LOW);
        same!("MEDIUM", sys::RTC_BUILD_QUALITY_MEDIUM);
        same!("FLOAT3", sys::RTC_FORMAT_FLOAT3);
        same!("UINT3", sys::RTC_FORMAT_UINT3);
        same!("VERTEX", sys::RTC_BUFFER_TYPE_VERTEX);
        same!("INDEX", sys::RTC_BUFFER_TYPE_INDEX);
        same!("TRIANGLE", sys::RTC_GEOMETRY_TYPE_TRIANGLE);
        same!("COHERENT", sys::RTC_INTERSECT_CONTEXT_FLAG_COHERENT);
        same!("INCOHERENT", sys::RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT);
        same!("NONE", sys::RTC_SCENE_FLAG_NONE);
        same!("VERSION", sys::RTC_DEVICE_PROPERTY_VERSION);
        same!("INVALID", sys::RTC_INVALID_GEOMETRY_ID);
        same!("ssize_t", size_of::<isize>());
        same!("instances", sys::RTCIntersectContext::init().inst_id.len());
    }

    #[test]
    fn bad_meshes_are_errors() {
        let v = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let e = EMesh::new(&v, &[[0, 1, 3]]).expect_err("index 3 of 3");
        assert!(e.to_string().contains("vertex 3"), "{e}");
        assert!(EMesh::new(&v, &[]).is_err());
        let e = obvhs::Bvh::build(&v, &[[0, 1, 7]]).expect_err("index 7 of 3");
        assert!(e.to_string().contains("vertex 7"), "{e}");
        let nan = [Vec3::ZERO, Vec3::X, Vec3::new(f32::NAN, 0.0, 0.0)];
        assert!(obvhs::Bvh::build(&nan, &[[0, 1, 2]]).is_err());
        let (mut b, _) = obvhs::Bvh::build(&v, &[[0, 1, 2]]).unwrap();
        assert!(b.rebuild(&v[..2]).is_err());
        assert!(b.rebuild(&v).is_ok());
    }

    /// `rebuild` of each side keeps answering as the fresh build does.
    #[test]
    fn rebuilds_trace_like_fresh_builds() {
        let s =
            scene::load_with("builtin:mixed", &SceneOptions::default().with_prims(5000)).unwrap();
        let p = Protocol::new(triangles(&s), CameraMode::Outside, 64);
        let dev = Device::new(1).unwrap();
        let mesh = EMesh::new(&s.vertices, &s.indices).unwrap();
        let (mut es, _) = EScene::build(&dev, &mesh, Quality::Low).unwrap();
        let before = p.run(&es, 1).counts;
        es.rebuild().unwrap();
        assert_eq!(p.run(&es, 1).counts, before);
        let (mut ob, _) = obvhs::Bvh::build(&s.vertices, &s.indices).unwrap();
        let ob_before = p.run(&ob, 1).counts;
        ob.rebuild(&s.vertices).unwrap();
        assert_eq!(p.run(&ob, 1).counts, ob_before);
        assert!(es.memory_bytes() > 0 && ob.memory_bytes() > 0);
    }

    /// Embree's dynamic scenes (geometry at REFIT, and at LOW) follow the moved vertices of
    /// `builtin:wave`: frame by frame their primary hits are those of a fresh emc build of the
    /// frame (within two rays of 4096) and of emc's refitted `Accel` (exactly).
    #[test]
    fn animated_scenes_follow_the_frames() {
        use emc_cpu::peers::embree::{Animated, Update};
        use emc_cpu::scene::builtin;
        let side = builtin::wave_side(6000);
        let idx = builtin::wave_indices(side);
        let v0 = builtin::wave_vertices(side, 0);
        let dev = Device::new(1).unwrap();
        let (mut refit, _) = Animated::build(&dev, &v0, &idx, Update::Refit).unwrap();
        let (mut low, _) = Animated::build(&dev, &v0, &idx, Update::Low).unwrap();
        let opts = BuildOptions::preset(Preset::Fast);
        let mut ours = Accel::build(&v0, &idx, &opts).unwrap();
        for frame in [5, 30, 60] {
            let v = builtin::wave_vertices(side, frame);
            assert!(refit.update(&v).unwrap() > std::time::Duration::ZERO);
            low.update(&v).unwrap();
            ours.refit(&v).unwrap();
            let tris: Vec<[Vec3; 3]> = idx.iter().map(|t| t.map(|i| v[i as usize])).collect();
            let p = Protocol::new(tris, CameraMode::Outside, 64);
            let fresh = Accel::build(&v, &idx, &opts).unwrap();
            let hits = |t: &dyn Tracer| p.run(t, 1).counts.primary_hits as i64;
            let want = hits(&fresh);
            assert_eq!(hits(&ours), want, "frame {frame}: emc refit");
            for (name, got) in [("REFIT", hits(&refit)), ("LOW", hits(&low))] {
                assert!(
                    (got - want).abs() <= 2,
                    "frame {frame}: embree {name} {got} vs {want}"
                );
            }
        }
        assert!(refit.update(&v0[1..]).is_err());
    }

    /// The harness folder `../shared/peers`, if present.
    fn harness_dir() -> Option<PathBuf> {
        let d = scene::shared_scenes_dir()?.parent()?.join("peers");
        d.join("build.sh").is_file().then_some(d)
    }

    fn read_f32s(p: &PathBuf) -> Vec<u32> {
        std::fs::read(p)
            .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }

    /// Rays (6 words each) that differ, with the first one's index.
    fn differing_rays(got: &[u32], want: &[u32]) -> (usize, Option<usize>) {
        assert_eq!(got.len(), want.len(), "ray counts");
        let bad: Vec<usize> = (0..got.len() / 6)
            .filter(|&i| got[6 * i..6 * i + 6] != want[6 * i..6 * i + 6])
            .collect();
        if let Some(&i) = bad.first() {
            let f = |w: &[u32]| w.iter().map(|&b| f32::from_bits(b)).collect::<Vec<_>>();
            eprintln!(
                "first differing ray {i}: got {:?}, want {:?}",
                f(&got[6 * i..6 * i + 6]),
                f(&want[6 * i..6 * i + 6])
            );
        }
        (bad.len(), bad.first().copied())
    }

    fn ray_bits(rays: &[emc_cpu::trace::Ray]) -> Vec<u32> {
        rays.iter()
            .flat_map(|r| {
                [
                    r.origin.x, r.origin.y, r.origin.z, r.dir.x, r.dir.y, r.dir.z,
                ]
                .map(f32::to_bits)
            })
            .collect()
    }

    /// Embree in process and the harness (built from `../shared/peers`, run with `--dump`) on
    /// the same OBJ: the same primary and AO rays bit for bit, the same hit distance and
    /// triangle per primary ray, the same occlusion per AO ray, and so the same counts.
    #[test]
    fn embree_answers_as_the_harness_on_a_small_scene() {
        let Some(peers) = harness_dir() else {
            eprintln!("skipping: ../shared/peers is absent");
            return;
        };
        let dir = Scratch::new("harness");
        let build = dir.join("harness");
        let st = Command::new("sh")
            .arg(peers.join("build.sh"))
            .env("PEERS_BUILD", &build)
            .status()
            .expect("sh runs");
        assert!(st.success(), "../shared/peers/build.sh failed");
        let generated =
            scene::load_with("builtin:city", &SceneOptions::default().with_prims(4000)).unwrap();
        let obj = dir.join("city.obj");
        scene::obj::save_obj(&generated, &obj).unwrap();
        let s = scene::load(obj.to_str().unwrap()).unwrap();
        let res = 128u32;
        let prefix = dir.join("dump");
        let out = Command::new(build.join("embree_bench"))
            .arg(&obj)
            .args([
                "--name",
                "city",
                "--cam",
                "outside",
                "--quality",
                "low,medium",
            ])
            .args(["--threads", "1", "--reps", "1", "--trace-reps", "1"])
            .args([
                "--res",
                &res.to_string(),
                "--packets",
                "0",
                "--bvh2-sah",
                "0",
            ])
            .arg("--dump")
            .arg(&prefix)
            .output()
            .expect("embree_bench runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let csv = String::from_utf8(out.stdout).unwrap();
        let mut lines = csv.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        let col = |row: &[&str], name: &str| -> u64 {
            row[header.iter().position(|h| *h == name).unwrap()]
                .parse()
                .unwrap()
        };
        let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
        assert_eq!(rows.len(), 2, "{csv}");

        let p = Protocol::new(triangles(&s), CameraMode::Outside, res);
        let dev = Device::new(1).unwrap();
        let mesh = EMesh::new(&s.vertices, &s.indices).unwrap();
        for (q, row) in [Quality::Low, Quality::Medium].into_iter().zip(&rows) {
            let f = |what: &str| {
                let mut name = prefix.clone().into_os_string();
                name.push(format!(".{}.{what}.bin", q.harness_name()));
                PathBuf::from(name)
            };
            let (es, _) = EScene::build(&dev, &mesh, q).unwrap();
            assert_eq!(
                ray_bits(&p.primary),
                read_f32s(&f("prim_rays")),
                "{q:?} rays"
            );
            let want_hits = read_f32s(&f("prim_hits"));
            let _ftz = FtzGuard::new();
            let (hits, _) = es.closest(&p.primary, 1);
            for (i, h) in hits.iter().enumerate() {
                let (t, prim) = (want_hits[2 * i], want_hits[2 * i + 1]);
                match h {
                    Some(h) => assert_eq!((h.t.to_bits(), h.prim), (t, prim), "{q:?} ray {i}"),
                    None => assert_eq!(prim, u32::MAX, "{q:?} ray {i} missed"),
                }
            }
            let ao = p.ao_rays(&hits);
            let d = differing_rays(&ray_bits(&ao), &read_f32s(&f("ao_rays")));
            assert_eq!(
                d,
                (0, None),
                "{q:?}: AO rays that differ (of {}), the first",
                ao.len()
            );
            let want_occ = std::fs::read(f("ao_occ")).unwrap();
            let mut ctx = sys::RTCIntersectContext::init();
            let occ: Vec<u8> = ao.iter().map(|r| es.occluded(r, &mut ctx) as u8).collect();
            assert_eq!(occ, want_occ, "{q:?}: per-ray occlusion");
            let run = p.run(&es, 1);
            let c = run.counts;
            assert_eq!(c.primary_hits, col(row, "primary_hits"), "{q:?}");
            assert_eq!(c.ao_rays, col(row, "ao_rays"), "{q:?}");
            assert_eq!(c.ao_occluded, col(row, "ao_occluded"), "{q:?}");
            assert!(c.primary_hits > 0 && c.ao_occluded > 0, "{q:?}: {c:?}");
            assert_eq!(p.run(&es, 2).counts, c, "{q:?}: two threads");
        }
    }

    /// The protocol bound on every count (`../shared/reference/peers.md`).
    const TOLERANCE: f64 = 5e-4;

    /// Embree LOW, obvhs and emc's fast preset on the shared scenes ≤ 1M triangles: counts
    /// within 0.05% of Embree's.
    #[test]
    fn counts_agree_on_the_shared_scenes() {
        if scene::shared_scenes_dir().is_none() {
            eprintln!("skipping: no shared scenes directory");
            return;
        }
        let threads = 2;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let dev = Device::new(threads).unwrap();
        let mut failures = Vec::new();
        let mut tested = 0;
        for name in ["sionna-san-francisco", "pbrt-bathroom", "stanford-dragon"] {
            if scene::shared_scene_path(name).is_none() {
                eprintln!("skipping {name}: not present");
                continue;
            }
            let s = scene::load(name).unwrap();
            let p =
                pool.install(|| Protocol::new(triangles(&s), CameraMode::for_scene(name), 1024));
            let mesh = EMesh::new(&s.vertices, &s.indices).unwrap();
            let (es, _) = EScene::build(&dev, &mesh, Quality::Low).unwrap();
            let want = p.run(&es, threads).counts;
            drop(es);
            let accel = pool
                .install(|| {
                    Accel::build(&s.vertices, &s.indices, &BuildOptions::preset(Preset::Fast))
                })
                .unwrap();
            let emc = p.run(&accel, threads).counts;
            drop(accel);
            let (ob, _) = pool
                .install(|| obvhs::Bvh::build(&s.vertices, &s.indices))
                .unwrap();
            let obv = p.run(&ob, threads).counts;
            eprintln!("{name}: Embree LOW {want:?}, emc fast {emc:?}, obvhs {obv:?}");
            for (who, got) in [("emc fast", emc), ("obvhs", obv)] {
                for (what, g, w) in [
                    ("primary hits", got.primary_hits, want.primary_hits),
                    ("AO rays", got.ao_rays, want.ao_rays),
                    ("AO occluded", got.ao_occluded, want.ao_occluded),
                ] {
                    let rel = (g as f64 - w as f64).abs() / w as f64;
                    if rel > TOLERANCE {
                        failures.push(format!("{name}: {who} {what} {g} vs Embree {w}"));
                    }
                }
            }
            tested += 1;
        }
        assert!(failures.is_empty(), "{}", failures.join("\n"));
        eprintln!("{tested} shared scenes checked");
    }

    /// Instances: emc's two-level `Scene` and Embree's instanced scene over the same mesh and
    /// transforms (rotated, scaled, mirrored, stretched) give the same primary hits ray for
    /// ray (instance and triangle ids; t within 1e-5 relative) except near ties and grazing
    /// rays (at most 0.05%), and AO counts within 0.05%, at both Embree top-level qualities.
    #[test]
    fn instanced_scene_agrees_with_embree_instances() {
        use emc_cpu::peers::embree::Instanced;
        use emc_cpu::peers::harness_ao_rays_by;
        use emc_cpu::trace::workload::{instance_grid, primary_rays, Camera, SceneFrame};
        use emc_cpu::trace::{Hit, Scene};
        use std::sync::Arc;

        let m =
            scene::builtin::generate("sphere", &SceneOptions::default().with_prims(4000)).unwrap();
        let (lo, hi) = m.vertices.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), v| (lo.min(*v), hi.max(*v)),
        );
        let xf = instance_grid(3000, lo, hi, 7);
        let mut blas = Scene::new();
        blas.add_mesh(
            &m.vertices,
            &m.indices,
            &BuildOptions::preset(Preset::Quality),
        )
        .unwrap();
        blas.commit().unwrap();
        let blas = Arc::new(blas);
        let mut top = Scene::new();
        for x in &xf {
            top.add_instance(blas.clone(), *x).unwrap();
        }
        top.commit().unwrap();
        let b = top.bounds();
        let frame = SceneFrame::of_box(b.min, b.max);
        let primary = primary_rays(&Camera::protocol(&frame, CameraMode::Outside), 256, 256);
        let tris = triangles(&m);
        let tri_of =
            |h: &Hit| tris[h.prim as usize].map(|v| xf[h.instance as usize].transform_point3(v));

        let dev = Device::new(1).unwrap();
        let mesh = EMesh::new(&m.vertices, &m.indices).unwrap();
        let (eblas, _) = Instanced::blas(&dev, &mesh).unwrap();
        let (mine, _) = Tracer::closest(&top, &primary, 1);
        let my_ao = harness_ao_rays_by(&primary, &mine, tri_of, frame.diag);
        let (my_occ, _) = Tracer::occluded(&top, &my_ao, 1);
        let hits = mine.iter().flatten().count();
        assert!(hits > 10_000, "only {hits} primary hits");
        for q in [Quality::Low, Quality::Medium] {
            let (es, _, _) = Instanced::build(&dev, &eblas, &xf, q).unwrap();
            let (theirs, _) = es.closest(&primary, 1);
            let mut differ = 0;
            for (i, (a, b)) in mine.iter().zip(&theirs).enumerate() {
                match (a, b) {
                    (Some(a), Some(b)) if (a.instance, a.prim) == (b.instance, b.prim) => {
                        // The two transform the ray with different roundings, which a
                        // grazing angle magnifies: beyond 1e-5 relative the ray counts as
                        // differing, beyond 1e-3 it is wrong.
                        let rel = (a.t - b.t).abs() / a.t.abs().max(b.t.abs());
                        assert!(rel <= 1e-3, "{q:?} ray {i}: t {} vs Embree {}", a.t, b.t);
                        differ += (rel > 1e-5) as usize;
                        assert_eq!((a.geom, b.geom), (0, 0));
                    }
                    (None, None) => {}
                    _ => differ += 1,
                }
            }
            let ao = harness_ao_rays_by(&primary, &theirs, tri_of, frame.diag);
            let (occ, _) = es.occluded(&ao, 1);
            // Each side's AO rays start at its own hits; on Embree's own rays the counts
            // differ only where the two triangle tests round differently (a few rays).
            let (mine_on_theirs, _) = Tracer::occluded(&top, &ao, 1);
            eprintln!(
                "{q:?}: {hits} primary hits, {differ} rays differ; AO occluded {my_occ} of {} vs Embree {occ} of {}; on Embree's AO rays emc finds {mine_on_theirs}",
                my_ao.len(),
                ao.len()
            );
            assert!(
                mine_on_theirs.abs_diff(occ) as f64 <= 2.0 + 1e-4 * occ as f64,
                "{q:?}: on the same AO rays emc finds {mine_on_theirs} occluded, Embree {occ}"
            );
            assert!(
                differ as f64 <= TOLERANCE * primary.len() as f64,
                "{q:?}: {differ} of {} primary rays differ from Embree",
                primary.len()
            );
            let rel = (my_occ as f64 - occ as f64).abs() / occ as f64;
            assert!(
                rel <= TOLERANCE,
                "{q:?}: AO occluded {my_occ} vs Embree {occ}"
            );
        }
    }
}
