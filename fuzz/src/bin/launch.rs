//! Fuzz target `launch`: see `microstereo::fuzzing::launch`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::launch(data));
}
