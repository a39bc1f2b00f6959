//! Tests of emc-hwsim's C ABI: the header in the repository matches the Rust signatures, the
//! committed golden vectors still equal the model and emc-core, and a C program compiled with
//! gcc against the static and the dynamic library reproduces them (codes and cycles).

use std::path::{Path, PathBuf};
use std::process::Command;

use emc_core::glam::Vec3;
use emc_core::{Aabb, Encoder, Frame, LayoutSpec};
use emc_hwsim::vectors::{parse, to_text, vectors};
use emc_hwsim::{RoutingChoice, Unit, UnitOptions};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A Rust FFI type as C spells it.
fn c_type(t: &str) -> String {
    let t = t.trim();
    if let Some(rest) = t.strip_prefix("*const ") {
        let inner = c_type(rest);
        return if inner.ends_with('*') {
            format!("{inner} const *")
        } else {
            format!("const {inner} *")
        };
    }
    if let Some(rest) = t.strip_prefix("*mut ") {
        let inner = c_type(rest);
        return if inner.ends_with('*') {
            format!("{inner}*")
        } else {
            format!("{inner} *")
        };
    }
    match t {
        "c_char" => "char",
        "usize" => "size_t",
        "u32" => "uint32_t",
        "u64" => "uint64_t",
        "f64" => "double",
        other => other,
    }
    .to_string()
}

/// `name(args) -> ret` of every `extern "C" fn` in ffi.rs, as C prototypes.
fn rust_prototypes() -> Vec<String> {
    let src = std::fs::read_to_string(root().join("emc-hwsim/src/ffi.rs")).unwrap();
    let mut out = Vec::new();
    for part in src.split("extern \"C\" fn ").skip(1) {
        let name = part.split('(').next().unwrap().trim();
        let close = part.find(')').unwrap();
        let args = &part[name.len() + 1..close];
        let after = &part[close + 1..part.find('{').unwrap()];
        let ret = after
            .trim()
            .strip_prefix("->")
            .map_or("void".to_string(), c_type);
        let params: Vec<String> = args
            .split(',')
            .filter(|a| !a.trim().is_empty())
            .map(|a| {
                let (n, t) = a.split_once(':').unwrap();
                format!("{} {}", c_type(t), n.trim())
            })
            .collect();
        out.push(norm(&format!("{ret} {name}({});", params.join(", "))));
    }
    out
}

/// Whitespace-insensitive form of a prototype (`T **x` and `T** x` alike).
fn norm(s: &str) -> String {
    s.split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
        .replace(" *", "*")
        .replace("* ", "*")
}

#[test]
fn hw_header_is_current() {
    let header = std::fs::read_to_string(root().join("emc-hwsim/include/emc_hwsim.h")).unwrap();
    let declared: Vec<String> = header
        .lines()
        .filter(|l| l.contains("emc_") && l.trim_end().ends_with(");"))
        .map(norm)
        .collect();
    let rust = rust_prototypes();
    assert_eq!(rust.len(), 9, "{rust:?}");
    for p in &rust {
        assert!(
            declared.contains(p),
            "header lacks or differs on `{p}`; it has {declared:#?}"
        );
    }
    assert_eq!(
        declared.len(),
        rust.len(),
        "header declares extra functions: {declared:#?}"
    );
    // The status codes and the box layout as C sees them.
    for (i, name) in [
        "OK",
        "NULL_POINTER",
        "BAD_LAYOUT",
        "BAD_SCENE",
        "BAD_CONFIG",
        "PANIC",
    ]
    .iter()
    .enumerate()
    {
        assert!(header.contains(&format!("EMC_{name} = {i}")), "EMC_{name}");
    }
    assert!(header.contains("float min[3];") && header.contains("float max[3];"));
}

/// The golden scene: 300 boxes of a small mixed scene, deterministic.
fn golden_scene() -> Vec<Aabb> {
    let mut s = 0x2545_f491_4f6c_dd1du64;
    let mut r = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    (0..300)
        .map(|i| {
            let p = Vec3::new(r() * 40.0 - 7.0, r() * 9.0, r() * 2.5 + (i % 3) as f32);
            Aabb::new(p, p + Vec3::new(r(), r() * 0.3, r() * r() * 4.0))
        })
        .collect()
}

const GOLDEN: [(&str, &str, u32); 3] = [
    ("emc64-var", "hwsim_golden_emc64var.vectors", 2),
    ("morton63", "hwsim_golden_morton63.vectors", 0),
    ("emc64-sort", "hwsim_golden_emc64sort.vectors", 3),
];

/// Every golden file equals what the model gives today, and its codes equal emc-core's.
/// `EMC_BLESS=1` rewrites them (after a deliberate change of the model).
#[test]
fn hw_golden_vectors_equal_the_model_and_emc_core() {
    let scene = golden_scene();
    let frame = Frame::new(&scene).unwrap();
    for (layout, file, routing) in GOLDEN {
        let spec: LayoutSpec = layout.parse().unwrap();
        let routing = [
            RoutingChoice::Auto,
            RoutingChoice::Fixed,
            RoutingChoice::Benes,
            RoutingChoice::Crossbar,
        ][routing as usize];
        let unit = Unit::for_spec(
            &spec,
            &frame,
            &UnitOptions {
                routing,
                ..UnitOptions::default()
            },
        )
        .unwrap();
        let text = to_text(&unit, &vectors(&unit, &scene));
        let path = root().join("tests/data").join(file);
        if std::env::var("EMC_BLESS").is_ok_and(|v| v == "1") {
            std::fs::write(&path, &text).unwrap();
        }
        let golden = std::fs::read_to_string(&path).unwrap();
        assert_eq!(
            golden, text,
            "{file} differs from the model (EMC_BLESS=1 rewrites it)"
        );
        let enc = Encoder::new(&spec, &frame);
        for v in parse(&golden).unwrap() {
            assert_eq!(v.code, enc.encode(&v.aabb));
        }
    }
}

/// The static and dynamic libraries of the emc-hwsim this test links (crate types staticlib and
/// cdylib): every build of emc-hwsim writes them beside its rlib in `deps/` in the same
/// compiler run (a package with a cdylib has no hash in its file names, so a later build
/// with other features writes over all three). Taken only when they were written with the
/// rlib (not more than a minute apart) and before this test was linked.
fn c_libraries() -> Option<(PathBuf, PathBuf)> {
    use std::time::Duration;
    let exe = std::env::current_exe().ok()?;
    let deps = exe.parent()?.to_path_buf();
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    let rlib = modified(&deps.join("libemc_hwsim.rlib"))?;
    let linked = modified(&exe)?;
    let fresh = |p: &Path| {
        modified(p).is_some_and(|t| {
            t + Duration::from_secs(60) >= rlib && t <= linked + Duration::from_secs(5)
        })
    };
    let (a, so) = (deps.join("libemc_hwsim.a"), deps.join("libemc_hwsim.so"));
    (fresh(&a) && fresh(&so)).then_some((a, so))
}

#[test]
fn hw_c_program_reproduces_the_golden_vectors() {
    if Command::new("gcc").arg("--version").output().is_err() {
        if std::env::var("EMC_REQUIRE_HW_TOOLS").is_ok_and(|v| v == "1") {
            panic!("gcc is missing; EMC_REQUIRE_HW_TOOLS=1 makes this a failure");
        }
        eprintln!("skipping: gcc is not installed");
        return;
    }
    let Some((a, so)) = c_libraries() else {
        let msg = "no libemc_hwsim.a/.so beside the emc-hwsim rlib this test links, written with \
                   it (a later build of emc-hwsim with other features replaced them: build \
                   this suite again)";
        if std::env::var("EMC_REQUIRE_HW_TOOLS").is_ok_and(|v| v == "1") {
            panic!("{msg}; EMC_REQUIRE_HW_TOOLS=1 makes this a failure");
        }
        eprintln!("skipping: {msg}");
        return;
    };
    let libdir = so.parent().unwrap();
    eprintln!("linking {} and {}", a.display(), so.display());
    let work = Path::new(env!("CARGO_TARGET_TMPDIR")).join("ffi");
    std::fs::create_dir_all(&work).unwrap();
    // The scene in the vectors format (codes and cycles unused by the reader's scene role).
    let mut scene_text = String::new();
    for b in golden_scene() {
        for f in b.min.to_array().iter().chain(b.max.to_array().iter()) {
            scene_text.push_str(&format!("{:08x} ", f.to_bits()));
        }
        scene_text.push_str("0 0 0\n");
    }
    let scene_file = work.join("scene.txt");
    std::fs::write(&scene_file, scene_text).unwrap();
    let src = root().join("tests/data/hwsim_ffi_test.c");
    let inc = root().join("emc-hwsim/include");
    for (kind, link) in [
        (
            "static",
            vec![
                a.display().to_string(),
                "-lpthread".into(),
                "-ldl".into(),
                "-lm".into(),
            ],
        ),
        (
            "dynamic",
            vec![
                format!("-L{}", libdir.display()),
                "-lemc_hwsim".into(),
                format!("-Wl,-rpath,{}", libdir.display()),
            ],
        ),
    ] {
        let prog = work.join(format!("ffi_test_{kind}"));
        let cc = Command::new("gcc")
            .args(["-std=c99", "-Wall", "-Wextra", "-Werror", "-O1"])
            .arg(format!("-I{}", inc.display()))
            .arg(&src)
            .args(&link)
            .arg("-o")
            .arg(&prog)
            .output()
            .unwrap();
        assert!(
            cc.status.success(),
            "gcc ({kind}): {}",
            String::from_utf8_lossy(&cc.stderr)
        );
        for (layout, file, routing) in GOLDEN {
            let run = Command::new(&prog)
                .arg(layout)
                .arg(routing.to_string())
                .arg(&scene_file)
                .arg(root().join("tests/data").join(file))
                .output()
                .unwrap();
            let out = String::from_utf8_lossy(&run.stdout);
            assert!(
                run.status.success() && out.contains("C PASS 300 vectors"),
                "{kind} {layout}: {out} {}",
                String::from_utf8_lossy(&run.stderr)
            );
            eprintln!("{kind} {layout}: {}", out.trim());
        }
    }
}
