//! Fuzz target `calibration`: see `microstereo::fuzzing::calibration`.

fn main() {
    afl::fuzz!(|data: &[u8]| microstereo::fuzzing::calibration(data));
}
