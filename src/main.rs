//! The `microstereo` binary: parses the command line and reports errors with exit code 2.

fn main() {
    std::process::exit(microstereo::cli::main());
}
