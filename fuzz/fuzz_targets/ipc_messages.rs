#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| xrce_common::fuzzing::ipc_messages(data));
