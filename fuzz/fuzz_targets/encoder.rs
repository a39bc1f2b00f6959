//! Fuzz target `encoder`: The encoder: random patterns and boxes, every backend against the reference.
//! The property lives in `emc_cpu::fuzzing::check_encoder`, which the corpus-replay test also runs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    emc_cpu::fuzzing::check_encoder(data);
});
