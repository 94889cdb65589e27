//! Fuzz target `pfm`: see `pipelines::fuzzing::pfm`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::pfm(data));
}
