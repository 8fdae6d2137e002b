#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| xrce_ipc::fuzzing::ipc_messages(data));
