use std::process::ExitCode;

fn main() -> ExitCode {
    pii_bake::cli::main()
}
