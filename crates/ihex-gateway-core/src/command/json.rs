//! The JSON text of a command as a tree that keeps what `serde_json::Value` hides: object members in
//! their order and every repeated key (so a duplicate can be refused instead of the last one
//! silently winning). Parsing is serde_json's (with its nesting limit); reading the tree is
//! `field`'s. Keys and strings borrow from the text when they have no escapes: a command's
//! members cost no allocation each.

use std::borrow::Cow;
use std::fmt;

use serde::de::{
    self, Deserialize, DeserializeSeed, Deserializer, IgnoredAny, MapAccess, SeqAccess, Visitor,
};
use serde_json::Number;

/// A JSON value, objects as member lists; strings borrowed from the text where they can be.
#[derive(Clone, PartialEq, Debug)]
pub enum Json<'a> {
    /// `null`.
    Null,
    /// `true` / `false`.
    Bool(bool),
    /// A number as written (integer or not).
    Number(Number),
    /// A string.
    String(Cow<'a, str>),
    /// An array.
    Array(Vec<Json<'a>>),
    /// An object: its members in order, repeated keys included.
    Object(Vec<(Cow<'a, str>, Json<'a>)>),
}

impl<'a> Json<'a> {
    /// Parses JSON text; the error is serde_json's (position included).
    pub fn parse(text: &'a str) -> Result<Json<'a>, serde_json::Error> {
        serde_json::from_str(text)
    }

    /// What kind of value this is, as a reason says it (`a string`, `an object`, …).
    pub fn kind(&self) -> &'static str {
        match self {
            Json::Null => "null",
            Json::Bool(_) => "a boolean",
            Json::Number(_) => "a number",
            Json::String(_) => "a string",
            Json::Array(_) => "an array",
            Json::Object(_) => "an object",
        }
    }
}

/// Longest quotation of a value in a reason; longer ones are cut with `…`.
const QUOTE_MAX: usize = 60;

/// The value as compact JSON, cut to a readable length: what a reason quotes after `got`.
pub struct Quote<'a>(pub &'a Json<'a>);

impl fmt::Display for Quote<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let text = self.0.to_string();
        match text.char_indices().nth(QUOTE_MAX) {
            Some((cut, _)) => write!(f, "{}…", &text[..cut]),
            None => f.write_str(&text),
        }
    }
}

impl fmt::Display for Json<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Json::Null => f.write_str("null"),
            Json::Bool(b) => write!(f, "{b}"),
            Json::Number(n) => write!(f, "{n}"),
            Json::String(s) => write_str(f, s),
            Json::Array(items) => {
                f.write_str("[")?;
                for (i, v) in items.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    write!(f, "{v}")?;
                }
                f.write_str("]")
            }
            Json::Object(members) => {
                f.write_str("{")?;
                for (i, (k, v)) in members.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    write_str(f, k)?;
                    write!(f, ":{v}")?;
                }
                f.write_str("}")
            }
        }
    }
}

/// A string as JSON text (quoted and escaped).
fn write_str(f: &mut fmt::Formatter<'_>, s: &str) -> fmt::Result {
    match serde_json::to_string(s) {
        Ok(quoted) => f.write_str(&quoted),
        Err(_) => write!(f, "{s:?}"),
    }
}

impl<'de> Deserialize<'de> for Json<'de> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Json<'de>, D::Error> {
        d.deserialize_any(JsonVisitor)
    }
}

/// An object key, borrowed from the text when it has no escapes (serde's own `Cow<str>` always
/// copies).
struct Key<'a>(Cow<'a, str>);

impl<'de> Deserialize<'de> for Key<'de> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Key<'de>, D::Error> {
        match d.deserialize_str(JsonVisitor)? {
            Json::String(s) => Ok(Key(s)),
            other => Err(de::Error::custom(format!("a key, not {}", other.kind()))),
        }
    }
}

struct JsonVisitor;

impl<'de> Visitor<'de> for JsonVisitor {
    type Value = Json<'de>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("any JSON value")
    }

    fn visit_unit<E: de::Error>(self) -> Result<Json<'de>, E> {
        Ok(Json::Null)
    }

    fn visit_bool<E: de::Error>(self, v: bool) -> Result<Json<'de>, E> {
        Ok(Json::Bool(v))
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<Json<'de>, E> {
        Ok(Json::Number(v.into()))
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<Json<'de>, E> {
        Ok(Json::Number(v.into()))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<Json<'de>, E> {
        // JSON text has no NaN or infinity, so this is always a number.
        Ok(Number::from_f64(v).map_or(Json::Null, Json::Number))
    }

    fn visit_borrowed_str<E: de::Error>(self, v: &'de str) -> Result<Json<'de>, E> {
        Ok(Json::String(Cow::Borrowed(v)))
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<Json<'de>, E> {
        Ok(Json::String(Cow::Owned(v.to_owned())))
    }

    fn visit_string<E: de::Error>(self, v: String) -> Result<Json<'de>, E> {
        Ok(Json::String(Cow::Owned(v)))
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Json<'de>, A::Error> {
        // Commands' arrays are short (a colour): one allocation instead of growing from empty.
        let mut items = Vec::with_capacity(seq.size_hint().unwrap_or(4).min(4));
        while let Some(v) = seq.next_element()? {
            items.push(v);
        }
        Ok(Json::Array(items))
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Json<'de>, A::Error> {
        // A command has a handful of members: one allocation instead of growing from empty.
        let mut members = Vec::with_capacity(map.size_hint().unwrap_or(8).min(8));
        while let Some((Key(k), v)) = map.next_entry::<Key<'de>, Json<'de>>()? {
            members.push((k, v));
        }
        Ok(Json::Object(members))
    }
}

/// The first string-valued member `key` of the top-level object in `bytes`, read as far as the
/// text is valid JSON (a syntax error after it, or a cut, does not lose it). Other values are
/// skipped without being stored, so this costs no memory whatever the size.
pub fn top_level_string(bytes: &[u8], key: &str) -> Option<String> {
    let mut found = None;
    let mut de = serde_json::Deserializer::from_slice(bytes);
    // An error only ends the scan: what was found before it stands.
    let _ = de.deserialize_any(Finder {
        key,
        found: &mut found,
    });
    found
}

/// Visits the top-level object, keeping the first string value of `key`.
struct Finder<'a> {
    key: &'a str,
    found: &'a mut Option<String>,
}

impl<'de> Visitor<'de> for Finder<'_> {
    type Value = ();

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a JSON object")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(k) = map.next_key::<std::borrow::Cow<'de, str>>()? {
            if k == self.key && self.found.is_none() {
                map.next_value_seed(StringOrSkip(self.found))?;
            } else {
                map.next_value::<IgnoredAny>()?;
            }
        }
        Ok(())
    }
}

/// A value that is stored when it is a string and skipped otherwise.
struct StringOrSkip<'a>(&'a mut Option<String>);

impl<'de> DeserializeSeed<'de> for StringOrSkip<'_> {
    type Value = ();

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> Visitor<'de> for StringOrSkip<'_> {
    type Value = ();

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("any JSON value")
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<(), E> {
        *self.0 = Some(v.to_owned());
        Ok(())
    }

    fn visit_bool<E: de::Error>(self, _: bool) -> Result<(), E> {
        Ok(())
    }

    fn visit_i64<E: de::Error>(self, _: i64) -> Result<(), E> {
        Ok(())
    }

    fn visit_u64<E: de::Error>(self, _: u64) -> Result<(), E> {
        Ok(())
    }

    fn visit_f64<E: de::Error>(self, _: f64) -> Result<(), E> {
        Ok(())
    }

    fn visit_unit<E: de::Error>(self) -> Result<(), E> {
        Ok(())
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        while seq.next_element::<IgnoredAny>()?.is_some() {}
        Ok(())
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while map.next_entry::<IgnoredAny, IgnoredAny>()?.is_some() {}
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn objects_keep_order_and_repeated_keys() {
        let j = Json::parse(r#"{"b":1,"a":[true,null,"x\"y"],"b":2.5}"#).unwrap();
        let Json::Object(m) = &j else { panic!() };
        let keys: Vec<&str> = m.iter().map(|(k, _)| k.as_ref()).collect();
        assert_eq!(keys, ["b", "a", "b"]);
        assert_eq!(j.to_string(), r#"{"b":1,"a":[true,null,"x\"y"],"b":2.5}"#);
    }

    #[test]
    fn keys_and_strings_borrow_from_the_text_unless_escaped() {
        let j = Json::parse(r#"{"cmd":"led","n\u006fde":"x\"y"}"#).unwrap();
        let Json::Object(m) = &j else { panic!() };
        assert!(matches!(
            m[0],
            (Cow::Borrowed("cmd"), Json::String(Cow::Borrowed("led")))
        ));
        let (key, Json::String(value)) = &m[1] else {
            panic!()
        };
        assert!(matches!(key, Cow::Owned(k) if k == "node"));
        assert!(matches!(value, Cow::Owned(v) if v == "x\"y"));
    }

    #[test]
    fn quotes_are_cut_to_a_readable_length() {
        let long = Json::String("x".repeat(100).into());
        let q = Quote(&long).to_string();
        assert_eq!(q.chars().count(), QUOTE_MAX + 1);
        assert!(q.ends_with('…'));
        assert_eq!(Quote(&Json::Number(7.into())).to_string(), "7");
    }

    #[test]
    fn a_top_level_string_is_found_before_any_error() {
        let find = |t: &str| top_level_string(t.as_bytes(), "request_id");
        assert_eq!(
            find(r#"{"a":[1,{"request_id":"inner"}],"request_id":"r1"}"#).as_deref(),
            Some("r1")
        );
        assert_eq!(
            find(r#"{"request_id":"r2","cmd": oops"#).as_deref(),
            Some("r2")
        );
        assert_eq!(
            find(r#"{"request_id":"r3","request_id":"r4"}"#).as_deref(),
            Some("r3")
        );
        assert_eq!(
            find(r#"{"request_id":7,"request_id":"r5"}"#).as_deref(),
            Some("r5")
        );
        assert_eq!(find(r#"{"cmd":"led","#), None);
        assert_eq!(find(r#"["request_id","x"]"#), None);
        assert_eq!(find("not json"), None);
        let big = format!(r#"{{"request_id":"big","pad":"{}"}}"#, "x".repeat(1 << 20));
        assert_eq!(
            find(&big[..1 << 19]).as_deref(),
            Some("big"),
            "a cut text keeps what was read"
        );
        let bytes = [
            br#"{"request_id":"r6","x":""#.as_slice(),
            &[0xff, 0xfe],
            br#""}"#,
        ]
        .concat();
        assert_eq!(
            top_level_string(&bytes, "request_id").as_deref(),
            Some("r6")
        );
    }

    #[test]
    fn nesting_is_limited_not_a_crash() {
        assert!(Json::parse(&"[".repeat(100_000)).is_err());
    }
}
