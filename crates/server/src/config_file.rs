//! `seasonloc serve --config FILE` (env `SEASONLOC_CONFIG`): the serve flags as a TOML file.
//!
//! Precedence, lowest first: a flag's default < the file < its environment variable < the
//! flag on the command line (as meilisearch and qdrant do). The file is turned into command-line
//! arguments for exactly the settings that neither the environment nor the command line gave,
//! and the command line is parsed again with them: every value goes through the same parser
//! and the same messages as a flag, so the file cannot accept what a flag refuses.
//!
//! Keys are the flags' long names in snake_case (`max_body_bytes`; the kebab-case spelling
//! `max-body-bytes` is accepted too). Values are TOML strings, integers, floats and booleans
//! (`allow_unauthenticated = true`); repeatable flags take arrays (`cors_origin = ["https://a"]`).
//! An unknown key, a nested table or a key naming `config` itself is refused with its name.

use std::ffi::OsString;
use std::path::Path;

use clap::parser::ValueSource;
use clap::{ArgAction, ArgMatches, Command};

/// Why a configuration file could not be used; the message names the file and the key.
#[derive(Debug, thiserror::Error)]
#[error("config file {path}: {reason}")]
pub struct ConfigFileError {
    /// The file as given.
    pub path: String,
    /// What is wrong, naming the key where one is at fault.
    pub reason: String,
}

/// The arguments `serve` gets from the TOML file at `path`: one `--flag=value` per setting
/// of the file whose flag `matches` (the parsed `serve` subcommand of `command`) took from
/// its default or not at all. Append them to the original command line and parse again.
pub fn file_args(
    path: &Path,
    command: &Command,
    matches: &ArgMatches,
) -> Result<Vec<OsString>, ConfigFileError> {
    let fail = |reason: String| ConfigFileError {
        path: path.display().to_string(),
        reason,
    };
    let text = std::fs::read_to_string(path).map_err(|e| fail(format!("cannot read it: {e}")))?;
    let table: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| fail(one_line(&e.to_string())))?;
    let mut out = Vec::new();
    for (key, value) in &table {
        let name = key.replace('-', "_");
        let arg = command
            .get_arguments()
            .find(|a| a.get_long().is_some_and(|l| l.replace('-', "_") == name))
            .filter(|_| name != "config")
            .ok_or_else(|| {
                fail(format!(
                    "unknown key `{key}` (the keys are the long flags of `seasonloc serve` in \
                     snake_case, e.g. `max_body_bytes`)"
                ))
            })?;
        let Some(long) = arg.get_long() else {
            continue;
        };
        if let Some(ValueSource::EnvVariable | ValueSource::CommandLine) =
            matches.value_source(arg.get_id().as_str())
        {
            continue;
        }
        let is_switch = matches!(arg.get_action(), ArgAction::SetTrue);
        let values: Vec<&toml::Value> = match value {
            toml::Value::Array(items) => {
                if !matches!(arg.get_action(), ArgAction::Append) {
                    return Err(fail(format!(
                        "`{key}` takes one value, not an array (only repeatable flags do)"
                    )));
                }
                items.iter().collect()
            }
            v => vec![v],
        };
        for v in values {
            let text = match v {
                toml::Value::String(s) => s.clone(),
                toml::Value::Integer(i) => i.to_string(),
                toml::Value::Float(f) => f.to_string(),
                toml::Value::Boolean(b) if is_switch => {
                    if *b {
                        out.push(OsString::from(format!("--{long}")));
                    }
                    continue;
                }
                toml::Value::Boolean(b) => b.to_string(),
                other => {
                    return Err(fail(format!(
                        "`{key}` must be a string, number or boolean, got a {}",
                        other.type_str()
                    )))
                }
            };
            if is_switch {
                return Err(fail(format!("`{key}` must be true or false, got `{text}`")));
            }
            out.push(OsString::from(format!("--{long}={text}")));
        }
    }
    Ok(out)
}

/// TOML's multi-line error reports (with a caret under the column) as one line.
fn one_line(text: &str) -> String {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.chars().all(|c| "|^ ".contains(c)))
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ServeArgs;
    use clap::{CommandFactory, FromArgMatches, Parser};

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        serve: ServeArgs,
    }

    /// Parses `argv` (after the program name), then again with the file's arguments, as the
    /// binary does.
    fn parse(file: &str, argv: &[&str]) -> Result<ServeArgs, String> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("seasonloc.toml");
        std::fs::write(&path, file).unwrap();
        let mut full: Vec<OsString> = vec!["seasonloc".into()];
        full.extend(argv.iter().map(OsString::from));
        let command = Cli::command();
        let matches = command.clone().try_get_matches_from(&full).unwrap();
        let extra = file_args(&path, &command, &matches).map_err(|e| e.to_string())?;
        full.extend(extra);
        let matches = command
            .try_get_matches_from(&full)
            .map_err(|e| e.to_string())?;
        Ok(Cli::from_arg_matches(&matches).unwrap().serve)
    }

    #[test]
    fn the_file_sets_what_the_command_line_does_not_and_flags_win() {
        let file = "max_body_bytes = 1000\nmax-batch-images = 7\nallow_unauthenticated = true\n\
                    cors_origin = [\"https://a.example\", \"https://b.example\"]\n\
                    addr = \"127.0.0.1:9001\"\n";
        let a = parse(file, &[]).unwrap();
        assert_eq!(a.max_body_bytes, 1000);
        assert_eq!(a.max_batch_images, 7);
        assert!(a.allow_unauthenticated);
        assert_eq!(a.cors_origins, ["https://a.example", "https://b.example"]);
        // The flag on the command line wins over the file.
        let b = parse(
            file,
            &["--max-body-bytes", "2000", "--addr", "127.0.0.1:9002"],
        )
        .unwrap();
        assert_eq!(b.max_body_bytes, 2000);
        assert_eq!(b.addr.port(), 9002);
        assert_eq!(b.max_batch_images, 7);
    }

    #[test]
    fn unknown_keys_bad_values_and_tables_are_refused_by_name() {
        let e = parse("max_body_byte = 10\n", &[]).unwrap_err();
        assert!(e.contains("unknown key `max_body_byte`"), "{e}");
        let e = parse("config = \"other.toml\"\n", &[]).unwrap_err();
        assert!(e.contains("unknown key `config`"), "{e}");
        let e = parse("max_body_bytes = \"lots\"\n", &[]).unwrap_err();
        assert!(e.contains("lots") && e.contains("--max-body-bytes"), "{e}");
        let e = parse("[server]\naddr = \"x\"\n", &[]).unwrap_err();
        assert!(e.contains("`server`"), "{e}");
        let e = parse("addr = [\"127.0.0.1:1\"]\n", &[]).unwrap_err();
        assert!(e.contains("`addr` takes one value"), "{e}");
        let e = parse("allow_unauthenticated = \"yes\"\n", &[]).unwrap_err();
        assert!(e.contains("true or false"), "{e}");
        let e = parse("addr = \n", &[]).unwrap_err();
        assert!(e.starts_with("config file ") && !e.contains('\n'), "{e}");
    }

    #[test]
    fn the_example_file_lists_valid_settings() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../seasonloc.example.toml");
        let text = std::fs::read_to_string(path).unwrap();
        let args = parse(&text, &[]).unwrap();
        args.validate().unwrap();
        // Every key of the example is a real setting and every setting is in the example.
        let table: toml::Table = text.parse().unwrap();
        let keys: std::collections::BTreeSet<String> = table.keys().cloned().collect();
        let flags: std::collections::BTreeSet<String> = Cli::command()
            .get_arguments()
            .filter_map(|a| a.get_long())
            .filter(|l| *l != "config")
            .map(|l| l.replace('-', "_"))
            .collect();
        let commented: std::collections::BTreeSet<String> = text
            .lines()
            .filter_map(|l| l.strip_prefix("# ")?.split_once(" = ").map(|(k, _)| k))
            .filter(|k| !k.contains(' '))
            .map(str::to_string)
            .collect();
        let all: std::collections::BTreeSet<String> = keys.union(&commented).cloned().collect();
        assert_eq!(all, flags, "seasonloc.example.toml vs the serve flags");
    }
}
