//! The `seasonloc` binary: parse the command line, run one subcommand, print its JSON on
//! stdout. Errors become one line on stderr and a non-zero exit code.

use std::process::ExitCode;

use std::ffi::OsString;

use clap::error::ErrorKind;
use clap::{CommandFactory, FromArgMatches};
mod cli;

use cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = match parse(std::env::args_os().collect()) {
        Ok(cli) => cli,
        Err(Usage::Clap(err)) => return usage_error(err),
        Err(Usage::ConfigFile(err)) => {
            eprintln!("seasonloc: {err}");
            return ExitCode::from(2);
        }
    };
    let result = match &cli.command {
        Command::Solve(args) => cli::solve::run(args).map(Some),
        Command::Eval(args) => cli::eval::run(args).map(Some),
        Command::Import(args) => cli::record::import(args).map(Some),
        // The estimates go to stdout unless --out names a file; the summary then goes to stderr.
        Command::Drive(args) => cli::record::drive(args).map(|summary| {
            if args.out.is_some() {
                Some(summary)
            } else {
                eprintln!("{summary}");
                None
            }
        }),
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

/// Why the command line could not be used.
enum Usage {
    Clap(clap::Error),
    ConfigFile(seasonloc_server::config_file::ConfigFileError),
}

/// Parses the command line; for `serve --config FILE` (or `SEASONLOC_CONFIG`), parses it again
/// with the file's settings appended, so that the file only supplies what the environment and
/// the flags left at their defaults ([`seasonloc_server::config_file`]).
fn parse(mut argv: Vec<OsString>) -> Result<Cli, Usage> {
    let matches = Cli::command()
        .try_get_matches_from(&argv)
        .map_err(Usage::Clap)?;
    let cli = Cli::from_arg_matches(&matches).map_err(Usage::Clap)?;
    let config = match &cli.command {
        Command::Serve(args) => args.config.clone().filter(|p| !p.as_os_str().is_empty()),
        _ => None,
    };
    let (Some(path), Some(serve)) = (config, matches.subcommand_matches("serve")) else {
        return Ok(cli);
    };
    let command = Cli::command();
    let Some(serve_command) = command.find_subcommand("serve") else {
        return Ok(cli);
    };
    let extra = seasonloc_server::config_file::file_args(&path, serve_command, serve)
        .map_err(Usage::ConfigFile)?;
    argv.extend(extra);
    // The first parse succeeded, so what fails now is a value of the file.
    let in_file = |err: clap::Error| {
        Usage::ConfigFile(seasonloc_server::config_file::ConfigFileError {
            path: path.display().to_string(),
            reason: usage_line(&err.render().to_string()),
        })
    };
    let matches = Cli::command()
        .try_get_matches_from(&argv)
        .map_err(in_file)?;
    Cli::from_arg_matches(&matches).map_err(in_file)
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
