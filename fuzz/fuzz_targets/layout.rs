//! Fuzz target `layout`: Layout parsing, resolution and the Display round trip.
//! The property lives in `emc_cpu::fuzzing::check_layout`, which the corpus-replay test also runs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    emc_cpu::fuzzing::check_layout(data);
});
