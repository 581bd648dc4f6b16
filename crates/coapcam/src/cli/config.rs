//! `serve --config FILE` and `serve --print-config`: a TOML file whose keys are `serve`'s
//! long flags (`grab-memory = 512`, `bind = ["0.0.0.0:5683"]`, `auto-measure = true`).
//! There is no second list of names: a key is looked up among the flags clap knows, so
//! a new flag (an output's own, flattened into `serve`) is a key with no code here. Each
//! key's value goes through its flag's own parser, alone, so an error names the key and
//! its line; then the keys become flags in front of the command line's, which override
//! them, and clap parses the whole as it parses flags. `--print-config` writes the
//! flags in effect as such a file.

use std::collections::BTreeMap;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

use clap::parser::ValueSource;
use clap::{ArgAction, ArgMatches, Command};
use coapcam::station::keys;
use coapcam::station::outputs::{self, Entry};
use toml::{Spanned, Value};

/// The subcommand a configuration file is for.
const SERVE: &str = "serve";
/// Flags that are not keys: they say where the keys are, or end the command.
const NOT_KEYS: [&str; 3] = ["help", "config", "print_config"];
/// The key of the file's list of outputs, `[[output]]` (a hidden flag, `--output`, with
/// one inline table per output).
const OUTPUT: &str = "output";
/// What a masked password reads as.
const MASK: &str = "********";

/// The process's command line parsed by `cmd`, exiting as clap does on an error. For
/// `serve --config FILE`, parsed again with the file's keys put in as the flags they name
/// (those given as flags are left out: the flags win); only then is it parsed twice.
/// `serve --print-config` prints the flags in effect as a file and exits 0; a file that
/// cannot be read, or a key or value it refuses, exits 2, as clap does for a bad flag.
pub(crate) fn command_line(cmd: Command) -> ArgMatches {
    let argv: Vec<OsString> = std::env::args_os().collect();
    let matches = cmd.clone().get_matches_from(&argv);
    let Some((SERVE, serve)) = matches.subcommand() else {
        return matches;
    };
    let mut serve_cmd = cmd.clone();
    serve_cmd.build();
    let serve_cmd = serve_cmd
        .find_subcommand(SERVE)
        .expect("serve is a subcommand")
        .clone();
    let at = argv
        .iter()
        .skip(1)
        .position(|a| a == SERVE)
        .map_or(argv.len(), |i| i + 2);
    let merged = |keys: &[FileKey], except: Option<usize>| {
        let mut merged = argv[..at].to_vec();
        for (i, key) in keys.iter().enumerate() {
            if Some(i) != except {
                merged.extend(key.words.iter().map(OsString::from));
            }
        }
        merged.extend_from_slice(&argv[at..]);
        merged
    };
    let matches = match serve.get_one::<PathBuf>("config") {
        Some(path) => {
            let keys = file_keys(path, &serve_cmd, serve).unwrap_or_else(|e| {
                eprintln!("coapcam: {e}");
                std::process::exit(2)
            });
            let all = merged(&keys, None);
            // The rules between flags (one requires another, two conflict), with the
            // file's: the keys without which the error goes are named.
            match cmd.clone().try_get_matches_from(&all) {
                Ok(matches) => matches,
                Err(e) => {
                    for (i, key) in keys.iter().enumerate() {
                        if cmd
                            .clone()
                            .try_get_matches_from(merged(&keys, Some(i)))
                            .is_ok()
                        {
                            eprintln!("coapcam: {}:{}: `{}`:", path.display(), key.line, key.name);
                        }
                    }
                    e.exit()
                }
            }
        }
        None => matches,
    };
    let (_, serve) = matches.subcommand().expect("serve");
    if serve.get_flag("print_config") {
        let (text, masked) = print(&serve_cmd, serve);
        print!("{text}");
        if !masked.is_empty() {
            eprintln!(
                "coapcam: the password in {} is masked ({MASK}): write it into the file by hand",
                masked.join(", ")
            );
        }
        std::process::exit(0);
    }
    matches
}

/// A key of the file, as the flags it stands for.
struct FileKey {
    name: String,
    line: usize,
    /// `--key=VALUE`, once per value; nothing for `false`.
    words: Vec<String>,
}

/// The keys of the file at `path`, in its order, as flags of `cmd`; those given on the
/// command line (`given`) are left out.
fn file_keys(path: &Path, cmd: &Command, given: &ArgMatches) -> Result<Vec<FileKey>, String> {
    let name = path.display();
    let text = std::fs::read_to_string(path).map_err(|e| format!("reading {name}: {e}"))?;
    let mut flags = Vec::new();
    for (key, value) in file_table(&text).map_err(|e| format!("{name}: {e}"))? {
        let line = line_of(&text, key.span().start);
        let at = |what: String| format!("{name}:{line}: {what}");
        if key.get_ref() == OUTPUT {
            if !matches!(value.get_ref(), Value::Array(tables) if tables.iter().all(Value::is_table))
            {
                return Err(at(format!(
                    "`{OUTPUT}` is a list of tables: [[{OUTPUT}]] with `{}` = one of {}, and that kind's keys",
                    outputs::KIND,
                    outputs::KINDS.join(", ")
                )));
            }
            let words = output_tables(&text)
                .map_err(|(line, why)| format!("{name}:{line}: {why}"))?
                .iter()
                .map(|entry| format!("--{OUTPUT}={entry}"))
                .collect();
            if given.value_source(OUTPUT) != Some(ValueSource::CommandLine) {
                flags.push(FileKey {
                    name: key.into_inner(),
                    line,
                    words,
                });
            }
            continue;
        }
        let arg = cmd
            .get_arguments()
            .find(|a| a.get_long() == Some(key.get_ref().as_str()))
            .filter(|a| !NOT_KEYS.contains(&a.get_id().as_str()))
            .ok_or_else(|| {
                at(format!(
                    "unknown key `{}` (the keys are serve's flags without their --: coapcam serve --help)",
                    key.get_ref()
                ))
            })?;
        let words = keys::words(arg, key.get_ref(), value.get_ref()).map_err(at)?;
        keys::check(arg, &words).map_err(|e| at(format!("`{}`: {e}", key.get_ref())))?;
        if given.value_source(arg.get_id().as_str()) != Some(ValueSource::CommandLine) {
            flags.push(FileKey {
                name: key.into_inner(),
                line,
                words,
            });
        }
    }
    Ok(flags)
}

/// The `[[output]]` tables of the file `text` as outputs, in its order; or the line at
/// fault and why: a key or value of a table refused, or a name given twice.
fn output_tables(text: &str) -> Result<Vec<Entry>, (usize, String)> {
    type SpannedTable = Spanned<BTreeMap<Spanned<String>, Spanned<Value>>>;
    #[derive(serde::Deserialize)]
    struct File {
        output: Vec<SpannedTable>,
    }
    let file: File = toml::from_str(text).map_err(|e| (1, e.message().to_owned()))?;
    let mut entries: Vec<Entry> = Vec::new();
    for spanned in file.output {
        let table_line = line_of(text, spanned.span().start);
        let key_line = |key: &str| {
            spanned
                .get_ref()
                .keys()
                .find(|k| k.get_ref() == key)
                .map_or(table_line, |k| line_of(text, k.span().start))
        };
        let table = spanned
            .get_ref()
            .iter()
            .map(|(k, v)| (k.get_ref().clone(), v.get_ref().clone()))
            .collect();
        let entry = Entry::from_table(table).map_err(|e| {
            let line = e.key.as_deref().map_or(table_line, &key_line);
            (line, format!("[[{OUTPUT}]]: {}", e.why))
        })?;
        if entries
            .iter()
            .any(|e| (e.kind(), e.name()) == (entry.kind(), entry.name()))
        {
            return Err((
                key_line(outputs::ID),
                format!(
                    "[[{OUTPUT}]]: a second output of kind \"{}\" named `{}`: give each output of a kind an `{}` of its own (it names the output's cursor in the results log)",
                    entry.kind(),
                    entry.name(),
                    outputs::ID
                ),
            ));
        }
        entries.push(entry);
    }
    Ok(entries)
}

/// A key of the file and its value, with where each is.
type Key = (Spanned<String>, Spanned<Value>);

/// The file's keys and values with where they are, in the file's order.
fn file_table(text: &str) -> Result<Vec<Key>, String> {
    let table: BTreeMap<Spanned<String>, Spanned<Value>> =
        toml::from_str(text).map_err(|e| e.to_string().trim_end().to_owned())?;
    let mut keys: Vec<_> = table.into_iter().collect();
    keys.sort_by_key(|(k, _)| k.span().start);
    Ok(keys)
}

/// The line (from 1) of byte `offset` of `text`.
fn line_of(text: &str, offset: usize) -> usize {
    text.get(..offset).unwrap_or(text).matches('\n').count() + 1
}

/// The flags of `matches` in effect as a configuration file: those given (on the command
/// line or in a file) as keys, the defaults as comments, in `cmd`'s order. Passwords in
/// URLs are masked; the second value names the keys that had one.
fn print(cmd: &Command, matches: &ArgMatches) -> (String, Vec<String>) {
    let mut text = String::from(
        "# coapcam serve --config: each key is a flag of `coapcam serve --help` without its\n\
         # --; a flag given on the command line overrides the key. Commented: defaults.\n\
         # More outputs, several of a kind: [[output]] tables (docs/station.md).\n",
    );
    let mut masked = Vec::new();
    for arg in cmd.get_arguments() {
        let id = arg.get_id().as_str();
        let Some(key) = arg.get_long() else { continue };
        if NOT_KEYS.contains(&id) || arg.is_hide_set() {
            continue;
        }
        let Some(raw) = matches.get_raw(id) else {
            continue;
        };
        let mut values: Vec<String> = raw.map(|v| v.to_string_lossy().into_owned()).collect();
        for v in &mut values {
            if let Some(hidden) = mask(v) {
                *v = hidden;
                masked.push(key.to_owned());
            }
        }
        let value = if !arg.get_action().takes_values() {
            values.first().cloned().unwrap_or_default()
        } else if matches!(arg.get_action(), ArgAction::Append) {
            let items: Vec<String> = values.iter().map(|v| scalar(v)).collect();
            format!("[{}]", items.join(", "))
        } else {
            values.first().map(|v| scalar(v)).unwrap_or_default()
        };
        let comment = match matches.value_source(id) {
            Some(ValueSource::CommandLine) => "",
            _ => "# ",
        };
        text.push_str(&format!("{comment}{key} = {value}\n"));
    }
    for entry in matches.get_many::<Entry>(OUTPUT).into_iter().flatten() {
        text.push_str(&format!("\n[[{OUTPUT}]]\n"));
        for (key, value) in entry.keys() {
            let value = match value.as_str().and_then(mask) {
                Some(hidden) => {
                    masked.push(format!("the [[{OUTPUT}]] `{}`'s `{key}`", entry.name()));
                    Value::String(hidden)
                }
                None => value.clone(),
            };
            text.push_str(&format!("{key} = {value}\n"));
        }
    }
    (text, masked)
}

/// `value` as TOML: an integer or a number when it reads back as the same text, else a
/// string.
fn scalar(value: &str) -> String {
    if value.parse::<i64>().is_ok_and(|i| i.to_string() == value)
        || (value.contains('.')
            && value
                .parse::<f64>()
                .is_ok_and(|f| f.is_finite() && f.to_string() == value))
    {
        value.to_owned()
    } else {
        Value::String(value.to_owned()).to_string()
    }
}

/// `value` with the password of a `SCHEME://USER:PASSWORD@HOST...` URL masked, if it has
/// one.
fn mask(value: &str) -> Option<String> {
    let (scheme, rest) = value.split_once("://")?;
    let end = rest.find('/').unwrap_or(rest.len());
    let (userinfo, _) = rest[..end].rsplit_once('@')?;
    let (user, password) = userinfo.split_once(':')?;
    (password != MASK).then(|| format!("{scheme}://{user}:{MASK}{}", &rest[userinfo.len()..]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passwords_are_masked_and_values_keep_their_type() {
        assert_eq!(
            mask("mqtt://dock:s3cret@10.0.0.2:1883/x").as_deref(),
            Some("mqtt://dock:********@10.0.0.2:1883/x")
        );
        assert_eq!(mask("mqtt://dock@10.0.0.2"), None);
        assert_eq!(mask("http://h/p?a=b:c@d"), None);
        assert_eq!(mask("mqtt://dock:********@h"), None);
        assert_eq!(scalar("512"), "512");
        assert_eq!(scalar("-40"), "-40");
        assert_eq!(scalar("0.25"), "0.25");
        assert_eq!(scalar("007"), "\"007\"");
        for text in ["a \"b\"", "it's", "x\ny", "0.10"] {
            let back: toml::Table = toml::from_str(&format!("k = {}", scalar(text))).unwrap();
            assert_eq!(back["k"].as_str(), Some(text), "{}", scalar(text));
        }
        assert_eq!(line_of("a = 1\n\nb = 2\n", 7), 3);
    }

    #[test]
    fn output_tables_of_two_kinds_may_share_a_name_but_not_of_one_kind() {
        let line = "[[output]]\nkind = \"line\"\nline-output = \"tcp://127.0.0.1:0\"\n";
        let webhook = |id: &str| {
            format!("[[output]]\nkind = \"webhook\"\nid = \"{id}\"\nwebhook = \"http://h/x\"\n")
        };
        let text = format!("{line}{}{}", webhook("line"), webhook("a"));
        let entries = output_tables(&text).expect("three outputs");
        let names: Vec<_> = entries.iter().map(|e| (e.kind(), e.name())).collect();
        assert_eq!(
            names,
            [("line", "line"), ("webhook", "line"), ("webhook", "a")]
        );
        let text = format!("{}{line}{}", webhook("a"), webhook("a"));
        let (at, why) = output_tables(&text).expect_err("two webhooks named a");
        assert_eq!(at, 10, "the second's id: {why}");
        assert!(why.contains("\"webhook\" named `a`"), "{why}");
    }
}
