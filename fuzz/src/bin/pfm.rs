//! Fuzz target `pfm`: see `microstereo::fuzzing::pfm`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::pfm(data));
}
