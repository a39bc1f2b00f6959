//! Replays every committed fuzz corpus file (`fuzz/corpus/<target>/`) through the same
//! property checks the `cargo fuzz` targets run (`emc_cpu::fuzzing`), so CI keeps every input
//! the fuzzer found interesting passing without libFuzzer.

use std::path::PathBuf;

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/corpus")
        .join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "{}: empty corpus", dir.display());
    files
        .into_iter()
        .map(|p| {
            let b = std::fs::read(&p).expect("corpus file");
            (p, b)
        })
        .collect()
}

fn replay(target: &str, check: fn(&[u8])) {
    let files = corpus(target);
    for (p, bytes) in &files {
        if std::panic::catch_unwind(|| check(bytes)).is_err() {
            panic!("{target}: {} fails its check", p.display());
        }
    }
    eprintln!("{target}: {} corpus files pass", files.len());
}

#[test]
fn obj_corpus() {
    replay("obj", emc_cpu::fuzzing::check_obj);
}

#[test]
fn layout_corpus() {
    replay("layout", emc_cpu::fuzzing::check_layout);
}

#[test]
fn encoder_corpus() {
    replay("encoder", emc_cpu::fuzzing::check_encoder);
}

#[test]
fn build_trace_corpus() {
    replay("build_trace", emc_cpu::fuzzing::check_build_trace);
}
