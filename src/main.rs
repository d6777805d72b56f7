//! The `seasonloc` binary: parse the command line, run one subcommand, print its JSON on
//! stdout. Errors become one line on stderr and a non-zero exit code.

use std::process::ExitCode;

use clap::error::ErrorKind;
use clap::Parser;
mod cli;

use cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(err) => return usage_error(err),
    };
    let result = match &cli.command {
        Command::Solve(args) => cli::solve::run(args).map(Some),
        Command::Eval(args) => cli::eval::run(args).map(Some),
        Command::Serve(args) => {
            seasonloc_server::service::run_serve(args.as_ref().clone()).map(|()| None)
        }
    };
    match result {
        Ok(Some(json)) => {
            println!("{json}");
            ExitCode::SUCCESS
        }
        Ok(None) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("seasonloc: {}", one_line(&err));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes joined by `: ` (as `{:#}` does), leaving out a cause whose text
/// its parent already ends with: several error types show their source in their own message
/// (`path: No such file or directory`) and also return it as `source()`.
fn one_line(err: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in err.chain() {
        let text = cause.to_string();
        if line.ends_with(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// Help and version go to stdout as clap renders them; every other parse error becomes one line
/// on stderr and exit code 2.
fn usage_error(err: clap::Error) -> ExitCode {
    match err.kind() {
        ErrorKind::DisplayHelp
        | ErrorKind::DisplayVersion
        | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => err.exit(),
        _ => {
            eprintln!("seasonloc: {}", usage_line(&err.render().to_string()));
            ExitCode::from(2)
        }
    }
}

/// Clap's message as one line: its first paragraph (the error and, for missing arguments, the
/// indented list that names them), without the tips and the usage block after it.
fn usage_line(rendered: &str) -> String {
    let line = rendered
        .lines()
        .take_while(|l| !l.trim().is_empty())
        .map(str::trim)
        .collect::<Vec<_>>()
        .join(" ");
    match line.trim_start_matches("error: ") {
        "" => "invalid arguments".to_owned(),
        text => text.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::usage_line;

    #[test]
    fn a_usage_error_keeps_the_names_of_missing_arguments_on_its_line() {
        let rendered = "error: the following required arguments were not provided:\n  \
                        --reference <REFERENCE>\n  --query <QUERY>\n\nUsage: seasonloc eval \
                        --reference <REFERENCE>\n\nFor more information, try '--help'.\n";
        assert_eq!(
            usage_line(rendered),
            "the following required arguments were not provided: --reference <REFERENCE> \
             --query <QUERY>"
        );
        let tip = "error: unexpected argument 'x' found\n\n  tip: use '-- x'\n\nUsage: s\n";
        assert_eq!(usage_line(tip), "unexpected argument 'x' found");
        assert_eq!(usage_line(""), "invalid arguments");
    }
}
