//! Reading the members of one command object: every field at most once, typed and range-checked as
//! it is read, every mistake a [`CommandError`] worded for the person who sent the command (the
//! field, what it accepts, what it got) — never a parser's internals.

use std::time::Duration;

use ihex_proto::unit;

use super::json::{Json, Quote};
use super::CommandError;

/// The fields of one JSON object of a command (the command itself, or `blink` inside `led`).
pub(crate) struct Fields<'a> {
    cmd: &'static str,
    /// `"blink."` for the members of `blink`, `""` at the top.
    prefix: &'static str,
    members: &'a [(&'a str, Json<'a>)],
}

/// Fields every command may have: `cmd`, then those listed as accepted besides its own.
pub(super) const COMMON: [&str; 5] = ["cmd", "request_id", "ttl_ms", "lease", "user"];

/// `ttl_ms` of `cmd`'s object (already checked for repeats by [`Fields::new`]).
pub(super) fn ttl(
    cmd: &'static str,
    members: &[(&str, Json<'_>)],
) -> Result<Option<Duration>, CommandError> {
    let f = Fields {
        cmd,
        prefix: "",
        members,
    };
    let max = i64::from(super::MAX_TTL_MS);
    let ms = f.int("ttl_ms", 1, max).map_err(|_| {
        let got = f.get("ttl_ms").unwrap_or(&Json::Null);
        f.bad("ttl_ms", &format!("an integer 1 to {max}, in ms"), got)
    })?;
    Ok(ms
        .and_then(|ms| u64::try_from(ms).ok())
        .map(Duration::from_millis))
}

/// `lease` of `cmd`'s object: the token of a lease its sender holds.
pub(super) fn lease(
    cmd: &'static str,
    members: &[(&str, Json<'_>)],
) -> Result<Option<String>, CommandError> {
    let f = Fields {
        cmd,
        prefix: "",
        members,
    };
    let expected = "the token of a lease, as `lease_granted` answered it";
    Ok(f.str("lease", expected)?.map(str::to_owned))
}

/// `user` of `cmd`'s object: the name the sender gives itself (claimed, not vouched for).
pub(super) fn user(
    cmd: &'static str,
    members: &[(&str, Json<'_>)],
) -> Result<Option<String>, CommandError> {
    let f = Fields {
        cmd,
        prefix: "",
        members,
    };
    Ok(f.str("user", "a name (recorded as claimed)")?
        .map(str::to_owned))
}

/// What a duration field accepts.
pub(crate) fn ms_expected() -> String {
    format!(
        "an integer {} to {}, in ms (rounded to the nearest 10 ms)",
        unit::MIN_MS,
        unit::MAX_MS
    )
}

impl<'a> Fields<'a> {
    /// The members of `cmd`'s object; refuses a repeated name, and any name not in `allowed`
    /// (the [`COMMON`] fields are allowed in every command; `hint` follows the list of accepted
    /// names in the reason).
    pub(crate) fn new(
        cmd: &'static str,
        prefix: &'static str,
        members: &'a [(&'a str, Json<'a>)],
        allowed: &[&str],
        hint: &str,
    ) -> Result<Fields<'a>, CommandError> {
        Fields::check(cmd, prefix, members, allowed, hint, prefix.is_empty())
    }

    /// The members of an object that is not a JSON API command (a Home Assistant payload): like
    /// [`Fields::new`] at the top, but `cmd` and `request_id` are as unknown as any other name.
    pub(crate) fn object(
        cmd: &'static str,
        members: &'a [(&'a str, Json<'a>)],
        allowed: &[&str],
    ) -> Result<Fields<'a>, CommandError> {
        Fields::check(cmd, "", members, allowed, "", false)
    }

    /// Refuses repeated and unknown names; `top`: `cmd` and `request_id` are allowed too.
    fn check(
        cmd: &'static str,
        prefix: &'static str,
        members: &'a [(&'a str, Json<'a>)],
        allowed: &[&str],
        hint: &str,
        top: bool,
    ) -> Result<Fields<'a>, CommandError> {
        for (i, (name, _)) in members.iter().enumerate() {
            if members[..i].iter().any(|(n, _)| n == name) {
                return Err(CommandError::Invalid {
                    cmd,
                    message: format!(
                        "duplicate field `{prefix}{name}` (each field may appear once)"
                    ),
                });
            }
            let common = top && COMMON.contains(name);
            if !common && !allowed.contains(name) {
                let mut accepted = allowed.to_vec();
                if top {
                    accepted.extend(&COMMON[1..]);
                }
                return Err(CommandError::Invalid {
                    cmd,
                    message: format!(
                        "unknown field `{prefix}{name}`; expected one of: {}{hint}",
                        accepted.join(", ")
                    ),
                });
            }
        }
        Ok(Fields {
            cmd,
            prefix,
            members,
        })
    }

    /// The value of `name`; `None` when it is absent or `null` ("not given").
    pub(crate) fn get(&self, name: &str) -> Option<&'a Json<'a>> {
        match self.members.iter().find(|(n, _)| *n == name) {
            None | Some((_, Json::Null)) => None,
            Some((_, v)) => Some(v),
        }
    }

    /// ``cmd: `field` must be EXPECTED; got VALUE``.
    pub(crate) fn bad(&self, name: &str, expected: &str, got: &Json<'_>) -> CommandError {
        self.invalid(format!(
            "`{}{name}` must be {expected}; got {}",
            self.prefix,
            Quote(got)
        ))
    }

    /// ``cmd: missing `field`: EXPECTED``.
    pub(crate) fn missing(&self, name: &str, expected: &str) -> CommandError {
        self.invalid(format!("missing `{}{name}`: {expected}", self.prefix))
    }

    /// `cmd: MESSAGE`.
    pub(crate) fn invalid(&self, message: String) -> CommandError {
        CommandError::Invalid {
            cmd: self.cmd,
            message,
        }
    }

    /// A required value: `v`, or the missing-field error.
    pub(crate) fn required<T>(
        &self,
        name: &str,
        v: Option<T>,
        expected: &str,
    ) -> Result<T, CommandError> {
        v.ok_or_else(|| self.missing(name, expected))
    }

    /// An integer from `lo` to `hi` (a JSON number without fraction or exponent beyond it).
    pub(crate) fn int(&self, name: &str, lo: i64, hi: i64) -> Result<Option<i64>, CommandError> {
        let Some(v) = self.get(name) else {
            return Ok(None);
        };
        match v {
            Json::Number(n) => match n.as_i64() {
                Some(i) if (lo..=hi).contains(&i) => Ok(Some(i)),
                _ => Err(self.bad(name, &format!("an integer {lo} to {hi}"), v)),
            },
            _ => Err(self.bad(name, &format!("an integer {lo} to {hi}"), v)),
        }
    }

    /// An integer from `lo` to `hi` as a byte.
    pub(crate) fn u8_in(&self, name: &str, lo: u8, hi: u8) -> Result<Option<u8>, CommandError> {
        let v = self.int(name, i64::from(lo), i64::from(hi))?;
        Ok(v.and_then(|i| u8::try_from(i).ok()))
    }

    /// An integer from `lo` to `hi` as a `u16`.
    pub(crate) fn u16_in(&self, name: &str, lo: u16, hi: u16) -> Result<Option<u16>, CommandError> {
        let v = self.int(name, i64::from(lo), i64::from(hi))?;
        Ok(v.and_then(|i| u16::try_from(i).ok()))
    }

    /// A duration in ms, as the protocol's 10 ms units (10–2550 ms, rounded to the nearest 10 ms).
    pub(crate) fn duration(&self, name: &str) -> Result<Option<u8>, CommandError> {
        let Some(v) = self.get(name) else {
            return Ok(None);
        };
        let units = match v {
            Json::Number(n) => n
                .as_u64()
                .and_then(|ms| u32::try_from(ms).ok())
                .and_then(unit::from_ms),
            _ => None,
        };
        units
            .map(Some)
            .ok_or_else(|| self.bad(name, &ms_expected(), v))
    }

    /// `true` or `false`.
    pub(crate) fn bool(&self, name: &str) -> Result<Option<bool>, CommandError> {
        match self.get(name) {
            None => Ok(None),
            Some(Json::Bool(b)) => Ok(Some(*b)),
            Some(v) => Err(self.bad(name, "true or false", v)),
        }
    }

    /// A string, described by `expected` when it is something else.
    pub(crate) fn str(&self, name: &str, expected: &str) -> Result<Option<&'a str>, CommandError> {
        match self.get(name) {
            None => Ok(None),
            Some(Json::String(s)) => Ok(Some(s)),
            Some(v) => Err(self.bad(name, expected, v)),
        }
    }
}
