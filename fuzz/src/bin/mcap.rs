//! Fuzz target `mcap`: see `microstereo::fuzzing::mcap`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::mcap(data));
}
