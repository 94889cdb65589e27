//! Fuzz target `bridge_line`: see `microstereo::fuzzing::bridge_line`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::bridge_line(data));
}
