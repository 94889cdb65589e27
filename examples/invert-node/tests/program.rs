//! The `microstereo-invert` program speaks the exec-node protocol on its own: it describes
//! its ports to the launch validator and refuses arguments it does not know. (Having an
//! integration test also makes `cargo test --workspace` build the program, which the
//! workspace's process-graph tests start.)

use std::process::Command;

fn invert() -> Command {
    Command::new(env!("CARGO_BIN_EXE_microstereo-invert"))
}

#[test]
fn the_program_describes_one_stereo_frame_in_and_one_out() {
    let out = invert().arg("--describe").output().unwrap();
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        String::from_utf8(out.stdout).unwrap().trim(),
        r#"{"inputs":[{"name":"frame","kind":"stereo-frame","optional":false}],"feedback":[],"outputs":[{"name":"frame","kind":"stereo-frame","optional":false}]}"#
    );
}

#[test]
fn unknown_parameters_and_arguments_are_refused_with_exit_code_2() {
    let out = invert()
        .args(["--describe", "--params", "gain = 2"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("gain"), "{err}");

    let out = invert().arg("--bogus").output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(String::from_utf8(out.stderr).unwrap().contains("--bogus"));
}
