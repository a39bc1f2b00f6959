//! Bad input through the built `emc` binary: every case must exit non-zero with exactly one
//! line on stderr that names the problem, and never panic. Skips (with a message) when the
//! binary is not built next to the test executable (`cargo build --release -p emc-cpu` first).

use std::path::PathBuf;
use std::process::Command;

/// `target/<profile>/emc`, next to the `deps` folder holding this test executable.
fn emc_binary() -> Option<PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let p = exe.parent()?.parent()?.join("emc");
    p.is_file().then_some(p)
}

/// A scratch file with `bytes` in a folder private to this test process.
fn scratch(name: &str, bytes: &[u8]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("emc-cli-errors-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let p = dir.join(name);
    std::fs::write(&p, bytes).expect("temp file");
    p
}

/// Run `emc args` and check the failure contract; `words` must all appear in the line.
fn expect_error(emc: &PathBuf, args: &[&str], words: &[&str]) {
    let out = Command::new(emc).args(args).output().expect("emc runs");
    let err = String::from_utf8_lossy(&out.stderr);
    let shown = format!(
        "emc {}: status {:?}, stderr:\n{err}",
        args.join(" "),
        out.status
    );
    assert!(!err.contains("panicked at"), "{shown}");
    assert!(out.status.code().is_some_and(|c| c != 0), "{shown}");
    let lines: Vec<&str> = err.lines().collect();
    assert_eq!(lines.len(), 1, "not exactly one line: {shown}");
    assert!(lines[0].starts_with("emc: "), "{shown}");
    for w in words {
        assert!(lines[0].contains(w), "`{w}` missing: {shown}");
    }
}

const TRI: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";

#[test]
fn malformed_obj_files() {
    let Some(emc) = emc_binary() else {
        eprintln!("the emc binary is not built next to this test; skipped");
        return;
    };
    let cases: Vec<(String, &str)> = vec![
        ("v 1 2\n".into(), "expected 3 coordinates"),
        ("v 0 0 0\nv 1 x 0\n".into(), "not a number"),
        ("v 0 0 0\nv 1 0 0 0 0\n".into(), "found 5 numbers"),
        ("v 0 0 0\nv 1 1 1 0\n".into(), "w = 0"),
        ("v 1e 0 0\n".into(), "not a number"),
        ("vn 1 2\n".into(), "expected 3 numbers"),
        ("vt x 0\n".into(), "not a number"),
        (format!("{TRI}f 1 2 4\n"), "index 4"),
        (format!("{TRI}f 0 1 2\n"), "index 0"),
        (format!("{TRI}f -1 -2 -4\n"), "index -4"),
        (format!("{TRI}f 1 2\n"), "at least 3 vertices"),
        (format!("{TRI}f 1 2 c\n"), "not a valid index"),
        (format!("{TRI}f 1/1/1/1 2 3\n"), "three `/` parts"),
        (format!("{TRI}f /1 2 3\n"), "no vertex index"),
        (
            format!("{TRI}vt 0 0\nf 1/2 2/1 3/1\n"),
            "texture coordinate index 2",
        ),
        (format!("{TRI}f 1//1 2//1 3//1\n"), "normal index 1"),
        (
            format!("{TRI}f 99999999999999999999999 1 2\n"),
            "not a valid index",
        ),
        (format!("{TRI}l 1\n"), "at least 2 vertices"),
        (format!("{TRI}usemtl\n"), "usemtl"),
        ("v 0 0 0\nv 1 0 0 1 1 1\n".into(), "colours"),
        (format!("f 1 2 3\n{TRI}"), "0 defined so far"),
        (
            "v 0 0 0\r\nv 1 0 0\r\nv 0 1\r\nf 1 2 3\r\n".into(),
            "expected 3 coordinates",
        ),
    ];
    for (k, (text, words)) in cases.iter().enumerate() {
        let p = scratch(&format!("bad{k}.obj"), text.as_bytes());
        let ps = p.to_str().expect("utf-8 temp path");
        expect_error(&emc, &["build", ps], &[words, &format!("bad{k}.obj")]);
    }
    // Invalid UTF-8 on a line.
    let p = scratch("utf8.obj", b"v 0 0 0\nv \xff 0 0\n");
    expect_error(&emc, &["build", p.to_str().unwrap()], &["utf8.obj"]);
}

#[test]
fn empty_and_missing_files() {
    let Some(emc) = emc_binary() else {
        eprintln!("the emc binary is not built next to this test; skipped");
        return;
    };
    let p = scratch("empty.obj", b"");
    expect_error(&emc, &["build", p.to_str().unwrap()], &["empty.obj"]);
    let p = scratch("verts.obj", TRI.as_bytes());
    expect_error(&emc, &["build", p.to_str().unwrap()], &["verts.obj"]);
    let p = scratch("nothing-here.obj", b"");
    let gone = p.with_file_name("does-not-exist.obj");
    expect_error(
        &emc,
        &["build", gone.to_str().unwrap()],
        &["does-not-exist.obj"],
    );
}

#[test]
fn bad_options() {
    let Some(emc) = emc_binary() else {
        eprintln!("the emc binary is not built next to this test; skipped");
        return;
    };
    let u = "builtin:uniform";
    expect_error(
        &emc,
        &["build", u, "--prims", "1000", "--layout", "morton99"],
        &["morton99"],
    );
    expect_error(
        &emc,
        &["layout", u, "--prims", "1000", "--layout", "zorder"],
        &["zorder"],
    );
    expect_error(
        &emc,
        &["build", u, "--prims", "1000", "--layout", "custom:xyzq"],
        &["custom:xyzq"],
    );
    // Wrong custom bit counts: 65 positions, and an empty pattern.
    let long = format!("custom:{}", "x".repeat(65));
    expect_error(
        &emc,
        &["build", u, "--prims", "1000", "--layout", &long],
        &["65"],
    );
    expect_error(
        &emc,
        &["build", u, "--prims", "1000", "--layout", "custom:"],
        &["custom"],
    );
    expect_error(
        &emc,
        &["build", u, "--prims", "1000", "--builder", "octree"],
        &["octree"],
    );
    for verb in ["build", "layout", "render"] {
        expect_error(
            &emc,
            &[verb, u, "--prims", "1000", "--threads", "0"],
            &["thread"],
        );
    }
    expect_error(
        &emc,
        &["build", "builtin:no-such-scene"],
        &["no-such-scene"],
    );
    expect_error(&emc, &["build", u, "--prims", "0"], &["--prims"]);
    expect_error(
        &emc,
        &[
            "render",
            u,
            "--prims",
            "1000",
            "--res",
            "16",
            "--kernels",
            "avx3",
        ],
        &["avx3"],
    );
    // A 4-wide test on the 8-wide tree.
    expect_error(
        &emc,
        &[
            "render",
            u,
            "--prims",
            "1000",
            "--res",
            "16",
            "--width",
            "8",
            "--kernels",
            "avx2,sse",
        ],
        &["sse", "8-wide"],
    );
    expect_error(
        &emc,
        &[
            "render",
            u,
            "--prims",
            "1000",
            "--res",
            "16",
            "--out",
            "/nonexistent-dir/x.png",
        ],
        &["/nonexistent-dir/x.png"],
    );
}
