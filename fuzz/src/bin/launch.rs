//! Fuzz target `launch`: see `pipelines::fuzzing::launch`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::launch(data));
}
