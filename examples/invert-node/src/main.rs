//! `microstereo-invert`: the invert node as a program of its own (an `exec` node). The
//! whole protocol — arguments, describing its ports to the launch validator, shared
//! memory, statistics — is `runtime::process::exec_main`.

use invert_node::Invert;
use runtime::Registry;

fn main() {
    std::process::exit(runtime::process::exec_main(
        Registry::new().task::<Invert>(),
    ));
}
