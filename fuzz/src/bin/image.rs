//! Fuzz target `image`: see `pipelines::fuzzing::image`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::image(data));
}
