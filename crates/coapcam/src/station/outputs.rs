//! The outputs of the results log, as one list. An output is a file of this folder with
//! its flags (a clap `Args` struct, which `serve` takes in through [`Outputs`]; its first
//! flag is the one that asks for it, the others say how), how it starts from them (`Args::configured`, and
//! `Args::start`, following the log through [`follow::run`](super::follow::run)) and what
//! it is once started (an [`Output`]). The outputs use `follow`, never this list, which
//! uses them. Adding one is its file and its name in the `outputs!` line below: that
//! name is its flags' group, its `kind` in a configuration file's `[[output]]` tables
//! (whose keys are its flags without their `--`), and the name of its cursor.
//!
//! Each flag gives one output, named by its kind; the `[[output]]` tables (the hidden
//! flag `--output`, one `{ kind = ..., ... }` inline table each, which `serve --config`
//! makes of them) give the others, each named by its `id`, which names its durable
//! cursor in the log ([`OutputId`]): two outputs of a kind keep positions of their own.

use std::collections::BTreeSet;
use std::fmt;

use clap::{Command, FromArgMatches as _};
use toml::{Table, Value};

use super::follow::{Feed, Output, OutputId};
use super::keys;

/// The key of an `[[output]]` table that says its kind.
pub const KIND: &str = "kind";
/// The key of an `[[output]]` table that names it.
pub const ID: &str = "id";

/// [`Outputs`], [`Settings`] and [`KINDS`]: every output's flags, flattened; one output's
/// settings; the kinds, in this order.
macro_rules! outputs {
    ($($name:ident),+) => {
        /// The outputs' flags: the `Args` of each, and the `[[output]]` tables.
        #[derive(Debug, Clone, Default, clap::Args)]
        pub struct Outputs {
            $(
                #[command(flatten)]
                $name: super::$name::Args,
            )+
            /// An output of a configuration file's `[[output]]` list, as an inline TOML
            /// table (`serve --config` gives each table as one).
            #[arg(long = "output", value_name = "TABLE", hide = true, value_parser = Entry::parse)]
            output: Vec<Entry>,
        }

        /// The kinds of output, by their name in `kind = "..."`.
        pub const KINDS: &[&str] = &[$(stringify!($name)),+];

        /// One output's settings: its kind's flags.
        #[derive(Debug, Clone)]
        // The variants are the kinds' names, as in a configuration file.
        #[allow(non_camel_case_types)]
        enum Settings {
            $($name(super::$name::Args),)+
        }

        impl Settings {
            /// The flags of kind `kind` as a command whose arguments are its keys.
            fn command(kind: &str) -> Option<Command> {
                match kind {
                    $(stringify!($name) => Some(<super::$name::Args as clap::Args>::augment_args(
                        Command::new(stringify!($name)).no_binary_name(true),
                    )),)+
                    _ => None,
                }
            }

            /// Kind `kind`'s settings from its flags parsed by [`Settings::command`].
            fn from_matches(kind: &str, matches: &clap::ArgMatches) -> Result<Self, String> {
                match kind {
                    $(stringify!($name) => super::$name::Args::from_arg_matches(matches)
                        .map(Self::$name)
                        .map_err(|e| keys::first_line(&e)),)+
                    _ => Err(unknown_kind(kind)),
                }
            }

            /// Its kind's name.
            fn kind(&self) -> &'static str {
                match self {
                    $(Self::$name(_) => stringify!($name),)+
                }
            }

            /// Starts it as output `id`.
            async fn start(
                &self,
                feed: &Feed<'_>,
                id: &OutputId,
            ) -> Result<Option<Box<dyn Output>>, OutputError> {
                match self {
                    $(Self::$name(args) => args
                        .start(feed, id)
                        .await
                        .map_err(|e| OutputError(Box::new(e))),)+
                }
            }
        }

        impl Outputs {
            /// The outputs the flags give, each named by its kind.
            fn flagged(&self) -> Vec<Settings> {
                let mut flagged = Vec::new();
                $(if self.$name.configured() {
                    flagged.push(Settings::$name(self.$name.clone()));
                })+
                flagged
            }
        }
    };
}

#[cfg(feature = "opcua")]
outputs!(mqtt, line, webhook, postgres, opcua);
#[cfg(not(feature = "opcua"))]
outputs!(mqtt, line, webhook, postgres);

/// One output of a configuration file's `[[output]]` list: its table, its id and its
/// kind's settings.
#[derive(Debug, Clone)]
pub struct Entry {
    table: Table,
    id: OutputId,
    settings: Settings,
}

/// An `[[output]]` table refused: why, and the key at fault (none: the table as a whole).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{why}")]
pub struct EntryError {
    /// The key at fault, if one is.
    pub key: Option<String>,
    /// Why, naming the key.
    pub why: String,
}

impl EntryError {
    fn at(key: &str, why: String) -> Self {
        Self {
            key: Some(key.to_owned()),
            why,
        }
    }
}

/// The kinds, quoted.
fn kinds() -> String {
    KINDS
        .iter()
        .map(|k| format!("\"{k}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Says which the kinds are.
fn unknown_kind(kind: &str) -> String {
    format!("`{KIND}` is one of {}, not {kind:?}", kinds())
}

impl Entry {
    /// The `[[output]]` table `text` (inline: `{ kind = "line", id = "a", ... }`); the
    /// parser of `--output`.
    pub fn parse(text: &str) -> Result<Self, EntryError> {
        let whole = |why: String| EntryError { key: None, why };
        let mut doc: Table = toml::from_str(&format!("output = {text}"))
            .map_err(|e| whole(format!("not a TOML table: {}", e.message())))?;
        match doc.remove("output") {
            Some(Value::Table(table)) => Self::from_table(table),
            _ => Err(whole("not a TOML table".into())),
        }
    }

    /// The output `table` asks for: `kind`, its `id` and the kind's flags as keys.
    pub fn from_table(table: Table) -> Result<Self, EntryError> {
        let kind = match table.get(KIND) {
            Some(Value::String(kind)) => kind.clone(),
            Some(_) | None => {
                return Err(EntryError {
                    key: table.contains_key(KIND).then(|| KIND.to_owned()),
                    why: format!("`{KIND}` is missing: one of {}", kinds()),
                });
            }
        };
        let command =
            Settings::command(&kind).ok_or_else(|| EntryError::at(KIND, unknown_kind(&kind)))?;
        let id = match table.get(ID) {
            None => None,
            Some(Value::String(id)) if valid_id(id) => Some(id.as_str()),
            Some(_) => {
                return Err(EntryError::at(
                    ID,
                    format!(
                        "`{ID}` is a name of letters, digits, `-`, `_` and `.` (it names the output's cursor in the results log)"
                    ),
                ));
            }
        };
        let mut words = Vec::new();
        for (key, value) in &table {
            if key == KIND || key == ID {
                continue;
            }
            let arg = command
                .get_arguments()
                .find(|a| a.get_long() == Some(key.as_str()))
                .ok_or_else(|| {
                    EntryError::at(
                        key,
                        format!(
                            "unknown key `{key}` for kind \"{kind}\" (its keys: {})",
                            [KIND, ID]
                                .into_iter()
                                .chain(command.get_arguments().filter_map(clap::Arg::get_long))
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    )
                })?;
            let these = keys::words(arg, key, value).map_err(|why| EntryError::at(key, why))?;
            keys::check(arg, &these)
                .map_err(|why| EntryError::at(key, format!("`{key}`: {why}")))?;
            words.extend(these);
        }
        // Its first flag asks for it; the others (`requires` it) only say how.
        let first = command
            .get_arguments()
            .find_map(clap::Arg::get_long)
            .unwrap_or_default();
        let whole = |why: String| EntryError { key: None, why };
        if !table.contains_key(first) {
            return Err(whole(format!("kind \"{kind}\" needs `{first}`")));
        }
        let matches = command
            .clone()
            .try_get_matches_from(&words)
            .map_err(|e| whole(keys::first_line(&e)))?;
        let settings = Settings::from_matches(&kind, &matches).map_err(whole)?;
        Ok(Self {
            id: OutputId::new(&kind, id),
            table,
            settings,
        })
    }

    /// Its name: its `id`, or its kind's.
    pub fn name(&self) -> &str {
        self.id.id().unwrap_or_else(|| self.settings.kind())
    }

    /// Its kind's name: with its name, what tells it apart from every other output (and
    /// names its cursor): two outputs of different kinds may have one name.
    pub fn kind(&self) -> &'static str {
        self.settings.kind()
    }

    /// Its keys and values: `kind`, `id`, then its kind's flags in their order.
    pub fn keys(&self) -> Vec<(&str, &Value)> {
        let order: Vec<String> = [KIND, ID]
            .into_iter()
            .map(str::to_owned)
            .chain(
                Settings::command(self.settings.kind())
                    .into_iter()
                    .flat_map(|c| {
                        c.get_arguments()
                            .filter_map(|a| a.get_long().map(str::to_owned))
                            .collect::<Vec<_>>()
                    }),
            )
            .collect();
        let mut keys: Vec<(&str, &Value)> =
            self.table.iter().map(|(k, v)| (k.as_str(), v)).collect();
        keys.sort_by_key(|(k, _)| order.iter().position(|o| o == k));
        keys
    }
}

impl fmt::Display for Entry {
    /// As the inline table `--output` takes.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("{ ")?;
        for (i, (key, value)) in self.keys().into_iter().enumerate() {
            if i > 0 {
                f.write_str(", ")?;
            }
            write!(f, "{key} = {value}")?;
        }
        f.write_str(" }")
    }
}

/// Whether `id` may name an output: letters, digits, `-`, `_`, `.`; not empty.
fn valid_id(id: &str) -> bool {
    !id.is_empty()
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

impl Outputs {
    /// Whether any output is asked for.
    pub fn any(&self) -> bool {
        !self.flagged().is_empty() || !self.output.is_empty()
    }

    /// Refuses two outputs of a kind with one name (two without an `id`, two `id`s alike:
    /// they would share a cursor), and an OPC UA server without users off this machine.
    /// Outputs of different kinds may have one name.
    pub fn check(&self) -> Result<(), String> {
        #[cfg(feature = "opcua")]
        for settings in self
            .flagged()
            .iter()
            .chain(self.output.iter().map(|e| &e.settings))
        {
            if let Settings::opcua(args) = settings {
                args.check()?;
            }
        }
        let mut names = BTreeSet::new();
        let flagged = self
            .flagged()
            .into_iter()
            .map(|s| (s.kind(), s.kind().to_owned()));
        let listed = self.output.iter().map(|e| (e.kind(), e.name().to_owned()));
        for (kind, name) in flagged.chain(listed) {
            if !names.insert((kind, name.clone())) {
                return Err(format!(
                    "two outputs of kind \"{kind}\" are named `{name}`: give each [[output]] of a kind an `{ID}` of its own"
                ));
            }
        }
        Ok(())
    }

    /// Refuses a station name an output asked for cannot carry: MQTT topic names allow a
    /// `/` (it separates levels), but the station's name is one level of
    /// `PREFIX/<station>/measurements`, which subscribers match with `+`.
    pub fn check_station(&self, station: &str) -> Result<(), super::mqtt::TargetError> {
        self.mqtt.check_station(station)?;
        for entry in &self.output {
            if let Settings::mqtt(args) = &entry.settings {
                args.check_station(station)?;
            }
        }
        Ok(())
    }

    /// Starts the outputs asked for, following `feed.log`: the flags' in the order of
    /// the list, then the `[[output]]` tables' in theirs.
    pub(super) async fn start(&self, feed: &Feed<'_>) -> Result<Vec<Box<dyn Output>>, OutputError> {
        let mut started = Vec::new();
        for settings in self.flagged() {
            started.extend(settings.start(feed, &OutputId::default()).await?);
        }
        for entry in &self.output {
            started.extend(entry.settings.start(feed, &entry.id).await?);
        }
        Ok(started)
    }
}

/// An output asked for could not start: its own error, as it says it (an address it
/// cannot listen on, a secret it cannot read, a station name its topics cannot carry).
/// Each output's error is its file's: a new output needs nothing here.
#[derive(Debug, thiserror::Error)]
#[error(transparent)]
pub struct OutputError(Box<dyn std::error::Error + Send + Sync>);

#[cfg(test)]
mod tests {
    use super::*;

    /// The outputs of `serve`'s output flags `words`.
    fn outputs(words: &[&str]) -> Outputs {
        use clap::Args as _;
        let command = Outputs::augment_args(Command::new("serve").no_binary_name(true));
        let matches = command.try_get_matches_from(words).expect("the flags");
        Outputs::from_arg_matches(&matches).expect("the outputs")
    }

    #[test]
    fn outputs_are_told_apart_by_their_kind_and_name_together() {
        let webhook =
            |id: &str| format!(r#"{{ kind = "webhook", id = "{id}", webhook = "http://h/x" }}"#);
        let (webhook_line, webhook_a, webhook_webhook) =
            (webhook("line"), webhook("a"), webhook("webhook"));
        let mqtt_a = r#"{ kind = "mqtt", id = "a", mqtt = "mqtt://h" }"#;
        let mqtt_webhook = r#"{ kind = "mqtt", id = "webhook", mqtt = "mqtt://h" }"#;
        // One name, two kinds: two cursors (`line` and `webhook/line`, `mqtt/a` and
        // `webhook/a`, `webhook` and `mqtt/webhook`).
        let apart = [
            vec![
                "--line-output",
                "tcp://127.0.0.1:0",
                "--output",
                &webhook_line,
            ],
            vec!["--output", mqtt_a, "--output", &webhook_a],
            vec!["--webhook", "http://h/y", "--output", mqtt_webhook],
        ];
        for words in apart {
            assert_eq!(outputs(&words).check(), Ok(()), "{words:?}");
        }
        // One kind, one name: one cursor.
        let alike = [
            (
                vec!["--output", &webhook_a, "--output", &webhook_a],
                "\"webhook\" are named `a`",
            ),
            (
                vec![
                    "--webhook",
                    "http://h/y",
                    "--output",
                    r#"{ kind = "webhook", webhook = "http://h/x" }"#,
                ],
                "\"webhook\" are named `webhook`",
            ),
            (
                vec!["--webhook", "http://h/y", "--output", &webhook_webhook],
                "\"webhook\" are named `webhook`",
            ),
        ];
        for (words, why) in alike {
            let e = outputs(&words)
                .check()
                .expect_err("two outputs of one kind and name");
            assert!(e.contains(why), "{words:?}: {e}");
        }
    }

    #[test]
    fn an_entry_reads_back_from_its_text_and_its_id_names_its_cursor() {
        let entry =
            Entry::parse(r#"{ webhook = "http://127.0.0.1:9/x", id = "wms", kind = "webhook" }"#)
                .expect("a webhook");
        assert_eq!(entry.name(), "wms");
        assert_eq!(entry.id.cursor("webhook"), "webhook/wms");
        let text = entry.to_string();
        assert_eq!(
            text,
            r#"{ kind = "webhook", id = "wms", webhook = "http://127.0.0.1:9/x" }"#
        );
        assert_eq!(Entry::parse(&text).expect("again").to_string(), text);
        // Without an id, or with its kind's name as one: the cursor of the flag's output.
        for text in [
            r#"{ kind = "webhook", webhook = "http://h/x" }"#,
            r#"{ kind = "webhook", id = "webhook", webhook = "http://h/x" }"#,
        ] {
            let entry = Entry::parse(text).expect("a webhook");
            assert_eq!(
                (entry.name(), entry.id.cursor("webhook").as_str()),
                ("webhook", "webhook")
            );
        }
        let e = Entry::parse(r#"{ kind = "line", line-output = "tcp://h:1" }"#).unwrap_err();
        assert_eq!(e.key.as_deref(), Some("line-output"), "{e}");
        let e = Entry::parse(r#"{ kind = "line", id = "a/b" }"#).unwrap_err();
        assert_eq!(e.key.as_deref(), Some("id"), "{e}");
    }

    /// An output that cannot start says why in its own words, each cause once, though
    /// the list has no variant for it: the line output's address taken, the MQTT
    /// publisher's station name that cannot be a topic level.
    #[tokio::test]
    async fn an_output_that_cannot_start_says_why_in_its_own_words() {
        let dir = crate::ScratchDir::new("outputs-start");
        let log = super::super::log::ResultsLog::open(&dir.path().join("log.db")).expect("log");
        let taken = std::net::TcpListener::bind("127.0.0.1:0").expect("a port");
        let addr = taken.local_addr().expect("its address");
        let feed = |station: &'static str| Feed {
            log: &log,
            station,
            state_dir: dir.path(),
            measure: None,
            cameras: std::sync::Arc::new(Vec::new),
        };
        let line = outputs(&["--line-output", &format!("tcp://{addr}")]);
        let e = line.start(&feed("lane-1")).await.err().expect("refused");
        let text = crate::error_text(&e);
        let listening = format!("listening for line output readers on {addr}: ");
        assert!(text.starts_with(&listening), "{text}");
        assert_eq!(text.matches(&listening).count(), 1, "{text}");
        let mqtt = outputs(&["--mqtt", "mqtt://127.0.0.1:9/p"]);
        let e = mqtt.start(&feed("a+b")).await.err().expect("refused");
        assert_eq!(
            crate::error_text(&e),
            "the station's name as an MQTT topic level (--station-name): \"a+b\" cannot be part of an MQTT topic name (no +, #, NUL, empty levels, or a / in the station name)"
        );
    }
}
