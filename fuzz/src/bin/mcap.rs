//! Fuzz target `mcap`: see `pipelines::fuzzing::mcap`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::mcap(data));
}
