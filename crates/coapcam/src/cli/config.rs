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

use clap::builder::Resettable;
use clap::parser::ValueSource;
use clap::{Arg, ArgAction, ArgMatches, Command};
use toml::{Spanned, Value};

/// The subcommand a configuration file is for.
const SERVE: &str = "serve";
/// Flags that are not keys: they say where the keys are, or end the command.
const NOT_KEYS: [&str; 3] = ["help", "config", "print_config"];
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
    let keys = keys(&text).map_err(|e| format!("{name}: {e}"))?;
    let mut flags = Vec::new();
    for (key, value) in keys {
        let line = line_of(&text, key.span().start);
        let at = |what: String| format!("{name}:{line}: {what}");
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
        let words = arg_words(arg, key.get_ref(), value.get_ref()).map_err(at)?;
        check(arg, &words).map_err(|e| at(format!("`{}`: {e}", key.get_ref())))?;
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

/// A key of the file and its value, with where each is.
type Key = (Spanned<String>, Spanned<Value>);

/// The file's keys and values with where they are, in the file's order.
fn keys(text: &str) -> Result<Vec<Key>, String> {
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

/// `key = value` as the words of a command line: `--key=VALUE` once per value, a flag
/// without a value when `true` and not at all when `false`.
fn arg_words(arg: &Arg, key: &str, value: &Value) -> Result<Vec<String>, String> {
    let flag = format!("--{key}");
    if !arg.get_action().takes_values() {
        return match value {
            Value::Boolean(true) => Ok(vec![flag]),
            Value::Boolean(false) => Ok(Vec::new()),
            _ => Err(format!("`{key}` is true or false")),
        };
    }
    let scalar = |v: &Value| match v {
        Value::String(s) => Ok(s.clone()),
        Value::Integer(i) => Ok(i.to_string()),
        Value::Float(f) => Ok(f.to_string()),
        Value::Boolean(b) => Ok(b.to_string()),
        _ => Err(format!(
            "`{key}` takes a string or a number, not {}",
            v.type_str()
        )),
    };
    let values = match (value, arg.get_action()) {
        (Value::Array(items), ArgAction::Append) => {
            items.iter().map(scalar).collect::<Result<_, _>>()?
        }
        (Value::Array(_), _) => return Err(format!("`{key}` takes one value, not a list")),
        (v, _) => vec![scalar(v)?],
    };
    Ok(values.into_iter().map(|v| format!("{flag}={v}")).collect())
}

/// Parses `words` (one flag's) with the flag alone: its parser's error, or nothing. The
/// rules between flags (requires, conflicts) are checked when all are parsed together.
fn check(arg: &Arg, words: &[String]) -> Result<(), String> {
    let alone = arg
        .clone()
        .required(false)
        .requires(Resettable::Reset)
        .conflicts_with(Resettable::Reset)
        .overrides_with(Resettable::Reset)
        .required_unless_present(Resettable::Reset);
    Command::new(SERVE)
        .no_binary_name(true)
        .disable_help_flag(true)
        .arg(alone)
        .try_get_matches_from(words)
        .map(drop)
        .map_err(|e| {
            let text = e.to_string();
            let first = text.lines().next().unwrap_or_default();
            first.trim_start_matches("error: ").to_owned()
        })
}

/// The flags of `matches` in effect as a configuration file: those given (on the command
/// line or in a file) as keys, the defaults as comments, in `cmd`'s order. Passwords in
/// URLs are masked; the second value names the keys that had one.
fn print(cmd: &Command, matches: &ArgMatches) -> (String, Vec<String>) {
    let mut text = String::from(
        "# coapcam serve --config: each key is a flag of `coapcam serve --help` without its\n\
         # --; a flag given on the command line overrides the key. Commented: defaults.\n",
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
}
