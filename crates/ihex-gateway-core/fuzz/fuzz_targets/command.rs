//! Fuzz target `command`: arbitrary bytes on the command topic of a gateway with a small island.
//! Nothing may panic and every input gets exactly one answer (see [`ihex_gateway_core_fuzz::command`]).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|input: &[u8]| ihex_gateway_core_fuzz::command(input));
