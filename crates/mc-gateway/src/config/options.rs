//! The machinery behind the options table of [`super`]: the `options!` macro turns one entry per
//! option into the layer struct ([`super::Options`]), the checked values ([`super::Settings`]),
//! the command line and the docs table. Nothing here names an option.

use std::{fmt::Display, net::SocketAddr, path::PathBuf, time::Duration};

use clap::Arg;

use crate::error::ConfigError;

/// A type an option can have: how clap reads it (TOML reads it with serde).
pub trait OptionType: Clone + Send + Sync + 'static {
    /// A switch: `--flag` alone means true, `--flag=false` switches off a file's `true`.
    const SWITCH: bool = false;
    /// What a value must be, as errors say it (`a whole number`).
    const WORD: &'static str;
    /// Sets the value parser.
    fn configure(arg: Arg) -> Arg;
}

macro_rules! option_types {
    ($($ty:ty => $word:literal),*) => {$(
        impl OptionType for $ty {
            const WORD: &'static str = $word;
            fn configure(arg: Arg) -> Arg {
                arg.value_parser(clap::value_parser!($ty))
            }
        }
    )*};
}
option_types!(
    String => "text",
    PathBuf => "a path",
    u8 => "a whole number",
    u16 => "a whole number",
    u32 => "a whole number",
    u64 => "a whole number",
    usize => "a whole number",
    SocketAddr => "an address ADDR:PORT (e.g. 127.0.0.1:1883 or [::1]:1883)"
);

impl OptionType for bool {
    const SWITCH: bool = true;
    const WORD: &'static str = "true or false";
    fn configure(arg: Arg) -> Arg {
        arg.value_parser(clap::value_parser!(bool))
            .num_args(0..=1)
            .require_equals(true)
            .default_missing_value("true")
    }
}

/// A default written in the table, turned into the option's type.
pub trait FromDefault<T> {
    /// The typed default.
    fn from_default(v: T) -> Self;
}

macro_rules! from_default_same {
    ($($ty:ty),*) => {$(
        impl FromDefault<$ty> for $ty {
            fn from_default(v: $ty) -> Self {
                v
            }
        }
    )*};
}
from_default_same!(bool, u8, u16, u32, u64, usize, SocketAddr);

impl FromDefault<&'static str> for String {
    fn from_default(v: &'static str) -> Self {
        v.to_owned()
    }
}

impl FromDefault<&'static str> for PathBuf {
    fn from_default(v: &'static str) -> Self {
        PathBuf::from(v)
    }
}

/// A duration default in whole milliseconds (the `*_ms` options).
pub fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// The flag of a TOML key (`health_period_ms` → `health-period-ms`), as errors name the option.
pub fn flag_name(key: &str) -> String {
    key.replace('_', "-")
}

/// How the docs show an option's default.
#[derive(Clone, Copy)]
pub enum DefaultText {
    /// No default: unset unless given.
    None,
    /// A sentence (the value is worked out from other options).
    Text(fn() -> String),
    /// A value, shown in backticks.
    Value(fn() -> String),
}

impl std::fmt::Debug for DefaultText {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.render())
    }
}

impl DefaultText {
    /// The docs' text.
    pub fn render(&self) -> String {
        match self {
            DefaultText::None => "–".into(),
            DefaultText::Text(t) => t(),
            DefaultText::Value(v) => format!("`{}`", v()),
        }
    }
}

/// The values an option accepts, when restricted.
#[derive(Clone, Copy, Debug)]
pub enum Accepted {
    /// Any value of its type.
    Any,
    /// A number from the first to the second (both as written in the table).
    Range(&'static str, &'static str),
    /// One of these words.
    OneOf(&'static [&'static str]),
}

impl Accepted {
    /// As the docs and `--help` say it; `None` for [`Accepted::Any`].
    pub fn render(&self, quote: &str) -> Option<String> {
        match self {
            Accepted::Any => None,
            Accepted::Range(lo, hi) => Some(format!("{lo} to {hi}")),
            Accepted::OneOf(words) => {
                let q: Vec<String> = words.iter().map(|w| format!("{quote}{w}{quote}")).collect();
                Some(match q.split_last() {
                    Some((last, init)) if !init.is_empty() => {
                        format!("{} or {last}", init.join(", "))
                    }
                    _ => q.concat(),
                })
            }
        }
    }
}

/// What the table says about one option.
#[derive(Clone, Copy, Debug)]
pub struct Spec {
    /// TOML key; the flag is the same with `-` for `_`.
    pub key: &'static str,
    /// Environment variable.
    pub env: &'static str,
    /// Placeholder of the value (`MS`, `HOST[:PORT]`).
    pub value: &'static str,
    /// Help text (the doc comment of the entry).
    pub help: &'static str,
    /// The default.
    pub default: DefaultText,
    /// The values it accepts.
    pub accepted: Accepted,
    /// Only on the command line or in the environment, not a TOML key (`config`).
    pub cli_only: bool,
    /// Its value is hidden from `--help` (`password`).
    pub secret: bool,
    /// A switch (`--flag[=BOOL]`).
    pub switch: bool,
    /// What a value must be ([`OptionType::WORD`]).
    pub word: &'static str,
}

impl Spec {
    /// The flag without dashes (`health-period-ms`).
    pub fn flag(&self) -> String {
        flag_name(self.key)
    }

    /// The help text, one line, without its final period.
    pub fn meaning(&self) -> &'static str {
        self.help.trim().trim_end_matches('.')
    }

    /// The command-line argument, without its value parser.
    pub fn arg(&self) -> Arg {
        let mut help = self.meaning().to_owned();
        if let Some(accepted) = self.accepted.render("") {
            help.push_str(&format!(" ({accepted})"));
        }
        if !matches!(self.default, DefaultText::None) {
            help.push_str(&format!(
                " [default: {}]",
                self.default.render().replace('`', "")
            ));
        }
        Arg::new(self.key)
            .long(self.flag())
            .env(self.env)
            .value_name(self.value)
            .help(help)
            .hide_env_values(self.secret)
    }

    /// What a value must be, with the accepted values: `a whole number from 1 to 1000`.
    pub fn expected(&self) -> String {
        match self.accepted {
            Accepted::Any => self.word.to_owned(),
            Accepted::Range(..) => format!(
                "{} from {}",
                self.word,
                self.accepted.render("").unwrap_or_default()
            ),
            Accepted::OneOf(_) => self.accepted.render("").unwrap_or_default(),
        }
    }

    /// The option's row of the docs table.
    pub fn docs_row(&self) -> String {
        let flag = if self.switch {
            format!("`--{}[={}]`", self.flag(), self.value)
        } else {
            format!("`--{} {}`", self.flag(), self.value)
        };
        let key = if self.cli_only {
            "–".to_owned()
        } else {
            format!("`{}`", self.key)
        };
        format!(
            "| {flag} | {key} | `{}` | {} | {} | {} |",
            self.env,
            self.default.render(),
            self.accepted.render("`").unwrap_or_default(),
            self.meaning()
        )
    }
}

/// A value as `--check-config` prints it.
pub trait Show {
    /// The text, `None` when unset.
    fn show(&self) -> Option<String>;
}

macro_rules! show_display {
    ($($ty:ty),*) => {$(
        impl Show for $ty {
            fn show(&self) -> Option<String> {
                Some(self.to_string())
            }
        }
    )*};
}
show_display!(String, bool, u8, u16, u32, u64, usize, SocketAddr);

impl Show for PathBuf {
    fn show(&self) -> Option<String> {
        Some(self.display().to_string())
    }
}

impl<T: Show> Show for Option<T> {
    fn show(&self) -> Option<String> {
        self.as_ref().and_then(Show::show)
    }
}

/// Where an option's value came from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Origin {
    /// The command line (`--flag`).
    Flag(String),
    /// The environment (`IHEX_…`).
    Env(&'static str),
    /// The `--config` file, this key.
    File(PathBuf, String),
    /// The default.
    Default,
}

impl Display for Origin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Origin::Flag(flag) => write!(f, "flag --{flag}"),
            Origin::Env(var) => write!(f, "environment variable {var}"),
            Origin::File(path, key) => write!(f, "file {}, key {key}", path.display()),
            Origin::Default => f.write_str("default"),
        }
    }
}

/// The range check of a number.
pub fn check_range<T: PartialOrd + Display>(
    key: &str,
    v: T,
    lo: T,
    hi: T,
) -> Result<T, ConfigError> {
    if v < lo || v > hi {
        return Err(ConfigError::invalid(
            flag_name(key),
            format!("{v} is not in the range {lo} to {hi}"),
        ));
    }
    Ok(v)
}

/// The check of a value restricted to a few words.
pub fn check_choice(key: &str, v: String, choices: &[&str]) -> Result<String, ConfigError> {
    if choices.contains(&v.as_str()) {
        return Ok(v);
    }
    let list = match choices {
        [init @ .., last] if !init.is_empty() => format!("{} or {last}", init.join(", ")),
        _ => choices.join(""),
    };
    Err(ConfigError::invalid(
        flag_name(key),
        format!("{v:?} is not {list}"),
    ))
}

/// The type of a field of `Settings`: the option's type when it has a default, else `Option`.
macro_rules! setting_type {
    ($ty:ty, none) => { Option<$ty> };
    ($ty:ty, (text $t:expr)) => { Option<$ty> };
    ($ty:ty, $d:tt) => { $ty };
}

/// How the docs show the default.
macro_rules! default_text {
    (none) => {
        $crate::config::options::DefaultText::None
    };
    ((text $t:expr)) => {
        $crate::config::options::DefaultText::Text(|| ($t).to_string())
    };
    ({$d:expr}) => {
        $crate::config::options::DefaultText::Value(|| ($d).to_string())
    };
    ($d:literal) => {
        $crate::config::options::DefaultText::Value(|| ($d).to_string())
    };
}

/// The value of a setting: the default applied, the range or choices checked.
macro_rules! setting_value {
    (@check $key:ident, $v:expr) => {
        Ok::<_, $crate::error::ConfigError>($v)
    };
    (@check $key:ident, $v:expr, $lo:literal, $hi:literal) => {
        $crate::config::options::check_range(stringify!($key), $v, $lo, $hi)
    };
    (@check $key:ident, $v:expr; $($c:literal),+) => {
        $crate::config::options::check_choice(stringify!($key), $v, &[$($c),+])
    };
    ($key:ident, $v:expr, $ty:ty, none) => {
        Ok::<_, $crate::error::ConfigError>($v)
    };
    ($key:ident, $v:expr, $ty:ty, (text $t:expr)) => {
        Ok::<_, $crate::error::ConfigError>($v)
    };
    ($key:ident, $v:expr, $ty:ty, {$d:expr} $($check:tt)*) => {
        setting_value!(@check $key, $v.unwrap_or_else(|| {
            <$ty as $crate::config::options::FromDefault<_>>::from_default($d)
        }) $($check)*)
    };
    ($key:ident, $v:expr, $ty:ty, $d:literal $($check:tt)*) => {
        setting_value!(@check $key, $v.unwrap_or_else(|| {
            <$ty as $crate::config::options::FromDefault<_>>::from_default($d)
        }) $($check)*)
    };
}

/// The options table: `/// help` lines, then `key: Type = default, env "IHEX_…", value "PLACEHOLDER"`
/// with optional `range LO..=HI`, `one_of ["a", "b"]` and markers `[cli_only, secret]`. The
/// default is `none`, `(text "what the docs say")` (the value is worked out in code), a literal, or
/// `{expression}`.
macro_rules! options {
    ($(
        $(#[doc = $doc:literal])+
        $key:ident: $ty:ty = $default:tt,
            env $env:literal, value $value:literal
            $(, range $lo:literal ..= $hi:literal)?
            $(, one_of [$($choice:literal),+])?
            $(, [$($marker:ident),*])?;
    )*) => {
        /// One layer of settings (the command line with the environment, or the TOML file): every
        /// option optional. [`Options::or`] stacks layers, [`Options::settings`] applies defaults.
        #[derive(Clone, Debug, Default, PartialEq, serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        pub struct Options {
            $(
                $(#[doc = $doc])+
                pub $key: Option<$ty>,
            )*
        }

        /// Every option with its default applied and its range checked (an option without a
        /// default stays an `Option`; the configuration works those out from the others).
        #[derive(Clone, Debug, PartialEq)]
        pub struct Settings {
            $(
                $(#[doc = $doc])+
                pub $key: setting_type!($ty, $default),
            )*
        }

        impl Settings {
            /// Every option's value as `--check-config` prints it, in table order (secrets
            /// hidden, unset options `None`).
            pub fn shown(&self) -> Vec<(&'static str, Option<String>)> {
                vec![$((
                    stringify!($key),
                    $crate::config::options::Show::show(&self.$key),
                ),)*]
            }
        }

        /// The table, in declaration order.
        pub fn specs() -> Vec<$crate::config::options::Spec> {
            vec![$(
                $crate::config::options::Spec {
                    key: stringify!($key),
                    env: $env,
                    value: $value,
                    help: concat!($($doc),+),
                    default: default_text!($default),
                    accepted: options!(@accepted $($lo, $hi)? $(; $($choice),+)?),
                    cli_only: options!(@has cli_only; $($($marker)*)?),
                    secret: options!(@has secret; $($($marker)*)?),
                    switch: <$ty as $crate::config::options::OptionType>::SWITCH,
                    word: <$ty as $crate::config::options::OptionType>::WORD,
                },
            )*]
        }

        impl Options {
            /// `self` where set, else `lower` (the command line over the file).
            pub fn or(self, lower: Options) -> Options {
                Options { $($key: self.$key.or(lower.$key),)* }
            }

            /// Applies the defaults and checks every range.
            pub fn settings(&self) -> Result<Settings, $crate::error::ConfigError> {
                Ok(Settings {
                    $($key: setting_value!($key, self.$key.clone(), $ty, $default $(, $lo, $hi)? $(; $($choice),+)?)?,)*
                })
            }

            /// The keys this layer sets, in table order.
            pub fn set_keys(&self) -> Vec<&'static str> {
                let mut keys = Vec::new();
                $(if self.$key.is_some() {
                    keys.push(stringify!($key));
                })*
                keys
            }

            /// The options a parsed command line (with its environment) gives.
            pub(crate) fn from_matches(m: &clap::ArgMatches) -> Options {
                Options { $($key: m.get_one::<$ty>(stringify!($key)).cloned(),)* }
            }

            /// The command-line arguments, in table order.
            pub(crate) fn args() -> Vec<clap::Arg> {
                specs()
                    .iter()
                    .zip([$(<$ty as $crate::config::options::OptionType>::configure as fn(clap::Arg) -> clap::Arg),*])
                    .map(|(spec, configure)| configure(spec.arg()))
                    .collect()
            }
        }
    };
    (@accepted) => {
        $crate::config::options::Accepted::Any
    };
    (@accepted $lo:literal, $hi:literal) => {
        $crate::config::options::Accepted::Range(stringify!($lo), stringify!($hi))
    };
    (@accepted ; $($c:literal),+) => {
        $crate::config::options::Accepted::OneOf(&[$($c),+])
    };
    (@has $want:ident;) => { false };
    (@has cli_only; cli_only $($rest:ident)*) => { true };
    (@has secret; secret $($rest:ident)*) => { true };
    (@has $want:ident; $other:ident $($rest:ident)*) => { options!(@has $want; $($rest)*) };
}

pub(crate) use {default_text, options, setting_type, setting_value};
