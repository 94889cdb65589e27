//! Fuzz target `bridge_line`: see `pipelines::fuzzing::bridge_line`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::bridge_line(data));
}
