//! The `rigbridge` binary: parses the command line and hands over to the library.

mod cli;

fn main() -> std::process::ExitCode {
    match cli::run() {
        Ok(code) => code,
        // The reader of our output went away (`| head`): the output ends there, cleanly.
        Err(_) if cli::stdout_closed() => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", rigbridge::daemon::error_chain(error.as_ref()));
            cli::exit_code_for(&error)
        }
    }
}
