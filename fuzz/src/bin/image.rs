//! Fuzz target `image`: see `microstereo::fuzzing::image`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::image(data));
}
