//! Fuzz target `calibration`: see `pipelines::fuzzing::calibration`.

fn main() {
    afl::fuzz!(|data: &[u8]| pipelines::fuzzing::calibration(data));
}
