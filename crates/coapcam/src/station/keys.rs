//! A configuration file's key as the flag it names: its TOML value as the words of a
//! command line ([`words`]), and those words checked by the flag's own parser, alone
//! ([`check`]). `serve --config` reads the file's keys with them (cli/config.rs), and
//! [`outputs`](super::outputs) the keys of an `[[output]]` table (its kind's flags).

use clap::builder::Resettable;
use clap::{Arg, ArgAction, Command};
use toml::Value;

/// `key = value` as the words of a command line: `--key=VALUE` once per value, a flag
/// without a value when `true` and not at all when `false`.
pub fn words(arg: &Arg, key: &str, value: &Value) -> Result<Vec<String>, String> {
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
pub fn check(arg: &Arg, words: &[String]) -> Result<(), String> {
    let alone = arg
        .clone()
        .required(false)
        .requires(Resettable::Reset)
        .conflicts_with(Resettable::Reset)
        .overrides_with(Resettable::Reset)
        .required_unless_present(Resettable::Reset);
    Command::new("key")
        .no_binary_name(true)
        .disable_help_flag(true)
        .arg(alone)
        .try_get_matches_from(words)
        .map(drop)
        .map_err(|e| first_line(&e))
}

/// A clap error's first line, without its `error: `.
pub fn first_line(e: &clap::Error) -> String {
    let text = e.to_string();
    let first = text.lines().next().unwrap_or_default();
    first.trim_start_matches("error: ").to_owned()
}
