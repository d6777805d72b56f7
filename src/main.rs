//! The `seasonloc` binary: parse the command line, run one subcommand, print its JSON on
//! stdout. Errors become one line on stderr and a non-zero exit code.

use std::process::ExitCode;

use clap::Parser;
use seasonloc::cli::{self, Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Solve(args) => cli::solve::run(args).map(Some),
        Command::Eval(args) => cli::eval::run(args).map(Some),
    };
    match result {
        Ok(Some(json)) => {
            println!("{json}");
            ExitCode::SUCCESS
        }
        Ok(None) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("seasonloc: {err:#}");
            ExitCode::FAILURE
        }
    }
}
