//! Fuzz target `build_trace`: Build and trace on tiny random meshes against brute force.
//! The property lives in `emc_cpu::fuzzing::check_build_trace`, which the corpus-replay test also runs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    emc_cpu::fuzzing::check_build_trace(data);
});
