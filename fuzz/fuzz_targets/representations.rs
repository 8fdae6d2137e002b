#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| xrce_dds_worker::fuzzing::representations(data));
