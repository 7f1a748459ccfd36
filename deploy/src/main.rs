//! The `handflow` command: see `handflow --help`.
fn main() -> std::process::ExitCode {
    handflow::cli::main()
}
