//! `seasonloc` command line. Temporary: only the `serve` subcommand (from the service branch);
//! the lead's CLI replaces this file and embeds `config::ServeArgs` the same way.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "seasonloc",
    version,
    about = "Visual localization across seasons"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the HTTP service on the embedded store.
    Serve(seasonloc::config::ServeArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => seasonloc::service::run_serve(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("seasonloc: {e:#}");
            ExitCode::FAILURE
        }
    }
}
