//! Fuzz target `obj`: The OBJ front end on arbitrary bytes.
//! The property lives in `emc_cpu::fuzzing::check_obj`, which the corpus-replay test also runs.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    emc_cpu::fuzzing::check_obj(data);
});
