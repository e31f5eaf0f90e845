//! The JSON text of a command as a tree that keeps what `serde_json::Value` hides: object members in
//! their order and every repeated key (so a duplicate can be refused instead of the last one
//! silently winning). Reading the tree is `field`'s. The tree lives in an [`Arena`] that the next
//! parse reuses: keys and strings borrow from the text when they have no escapes, and everything
//! else is bumped in the arena, so a command's tree costs no allocation of its own and nothing to
//! free.
//!
//! Parsing is serde_json's (its nesting limit, its error messages), except for the shape nearly
//! every command has — objects and arrays a few levels deep, strings without escapes or control
//! characters, integers of up to 18 digits, `true`, `false`, `null` — which a single pass reads
//! first (module `fast`): an LED command's parse took about 2,100 instructions through serde's
//! visitor, 1,650 this way (callgrind), of some 15,000 the gateway spends on it. Anything else, an
//! error included, makes that pass give up and serde_json parse the text from the start, so both
//! give the same tree for any text.

use std::fmt;

use bumpalo::collections::Vec as BumpVec;
use bumpalo::Bump;
use serde::de::{self, DeserializeSeed, Deserializer, IgnoredAny, MapAccess, SeqAccess, Visitor};
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
    String(&'a str),
    /// An array.
    Array(&'a [Json<'a>]),
    /// An object: its members in order, repeated keys included.
    Object(&'a [(&'a str, Json<'a>)]),
}

impl Json<'_> {
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

/// Memory for parsed trees, kept from one parse to the next. Allocating every object and array of
/// a command from the C allocator and freeing it again cost about a third of a command's
/// instructions (callgrind, musl's allocator); bumping in a reused block costs a few.
#[derive(Default)]
pub struct Arena(Bump);

/// Arena memory kept between parses at most: an unusually large payload's block is given back.
const ARENA_KEEP: usize = 16 * 1024;

impl Arena {
    /// Parses JSON text into a tree in this arena (the previous tree's memory is reused); the
    /// error is serde_json's (position included).
    pub fn parse<'a>(&'a mut self, text: &'a str) -> Result<Json<'a>, serde_json::Error> {
        if self.0.allocated_bytes() > ARENA_KEEP {
            self.0 = Bump::new();
        } else {
            self.0.reset();
        }
        if let Some(value) = fast::parse(text, &self.0) {
            return Ok(value);
        }
        let mut de = serde_json::Deserializer::from_str(text);
        let value = Seed(&self.0).deserialize(&mut de)?;
        de.end()?;
        Ok(value)
    }
}

impl fmt::Debug for Arena {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Arena")
            .field("allocated_bytes", &self.0.allocated_bytes())
            .finish()
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

/// Deserializes one value into the arena.
#[derive(Clone, Copy)]
struct Seed<'a>(&'a Bump);

impl<'de: 'a, 'a> DeserializeSeed<'de> for Seed<'a> {
    type Value = Json<'a>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Json<'a>, D::Error> {
        d.deserialize_any(self)
    }
}

/// An object key: borrowed from the text, or copied into the arena when it has escapes.
struct KeySeed<'a>(&'a Bump);

impl<'de: 'a, 'a> DeserializeSeed<'de> for KeySeed<'a> {
    type Value = &'a str;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<&'a str, D::Error> {
        match d.deserialize_str(Seed(self.0))? {
            Json::String(s) => Ok(s),
            other => Err(de::Error::custom(format!("a key, not {}", other.kind()))),
        }
    }
}

impl<'de: 'a, 'a> Visitor<'de> for Seed<'a> {
    type Value = Json<'a>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("any JSON value")
    }

    fn visit_unit<E: de::Error>(self) -> Result<Json<'a>, E> {
        Ok(Json::Null)
    }

    fn visit_bool<E: de::Error>(self, v: bool) -> Result<Json<'a>, E> {
        Ok(Json::Bool(v))
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<Json<'a>, E> {
        Ok(Json::Number(v.into()))
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<Json<'a>, E> {
        Ok(Json::Number(v.into()))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<Json<'a>, E> {
        // JSON text has no NaN or infinity, so this is always a number.
        Ok(Number::from_f64(v).map_or(Json::Null, Json::Number))
    }

    fn visit_borrowed_str<E: de::Error>(self, v: &'de str) -> Result<Json<'a>, E> {
        Ok(Json::String(v))
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<Json<'a>, E> {
        Ok(Json::String(self.0.alloc_str(v)))
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Json<'a>, A::Error> {
        // Commands' arrays are short (a colour): room for that from the start.
        let mut items = BumpVec::with_capacity_in(4, self.0);
        while let Some(v) = seq.next_element_seed(self)? {
            items.push(v);
        }
        Ok(Json::Array(items.into_bump_slice()))
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Json<'a>, A::Error> {
        // A command has a handful of members: room for that from the start.
        let mut members = BumpVec::with_capacity_in(8, self.0);
        while let Some(k) = map.next_key_seed(KeySeed(self.0))? {
            members.push((k, map.next_value_seed(self)?));
        }
        Ok(Json::Object(members.into_bump_slice()))
    }
}

/// The single pass for the common shape of a command (see the module's purpose line): `None` as
/// soon as the text leaves that shape, valid JSON or not.
mod fast {
    use super::{Bump, BumpVec, Json};

    /// Deeper nesting is left to serde_json (commands nest two levels).
    const DEPTH: u8 = 8;
    /// Longer integers are left to serde_json (an `i64` holds any 18 digits).
    const DIGITS: usize = 18;

    /// The text as a tree in `arena`, if it has the common shape.
    pub(super) fn parse<'a>(text: &'a str, arena: &'a Bump) -> Option<Json<'a>> {
        let mut p = Pass {
            text,
            pos: 0,
            arena,
        };
        let value = p.value(0)?;
        p.skip_ws();
        (p.pos == text.len()).then_some(value)
    }

    struct Pass<'a> {
        text: &'a str,
        pos: usize,
        arena: &'a Bump,
    }

    impl<'a> Pass<'a> {
        fn peek(&self) -> Option<u8> {
            self.text.as_bytes().get(self.pos).copied()
        }

        fn skip_ws(&mut self) {
            while let Some(b' ' | b'\t' | b'\n' | b'\r') = self.peek() {
                self.pos += 1;
            }
        }

        /// Skips whitespace, then takes `byte` if it comes next.
        fn eat(&mut self, byte: u8) -> bool {
            self.skip_ws();
            let next = self.peek() == Some(byte);
            self.pos += usize::from(next);
            next
        }

        fn value(&mut self, depth: u8) -> Option<Json<'a>> {
            self.skip_ws();
            match self.peek()? {
                b'{' if depth < DEPTH => self.object(depth + 1),
                b'[' if depth < DEPTH => self.array(depth + 1),
                b'"' => self.string().map(Json::String),
                b't' => self.word("true", Json::Bool(true)),
                b'f' => self.word("false", Json::Bool(false)),
                b'n' => self.word("null", Json::Null),
                b'-' | b'0'..=b'9' => self.integer(),
                _ => None,
            }
        }

        fn object(&mut self, depth: u8) -> Option<Json<'a>> {
            self.pos += 1;
            let mut members = BumpVec::with_capacity_in(8, self.arena);
            if !self.eat(b'}') {
                loop {
                    self.skip_ws();
                    if self.peek() != Some(b'"') {
                        return None;
                    }
                    let key = self.string()?;
                    if !self.eat(b':') {
                        return None;
                    }
                    members.push((key, self.value(depth)?));
                    if self.eat(b'}') {
                        break;
                    }
                    if !self.eat(b',') {
                        return None;
                    }
                }
            }
            Some(Json::Object(members.into_bump_slice()))
        }

        fn array(&mut self, depth: u8) -> Option<Json<'a>> {
            self.pos += 1;
            let mut items = BumpVec::with_capacity_in(4, self.arena);
            if !self.eat(b']') {
                loop {
                    items.push(self.value(depth)?);
                    if self.eat(b']') {
                        break;
                    }
                    if !self.eat(b',') {
                        return None;
                    }
                }
            }
            Some(Json::Array(items.into_bump_slice()))
        }

        /// A string without escapes or control characters, borrowed (at its opening quote).
        fn string(&mut self) -> Option<&'a str> {
            let start = self.pos + 1;
            let rest = self.text.as_bytes().get(start..)?;
            let len = crate::json_text::special_byte(rest)?;
            if rest[len] != b'"' {
                return None;
            }
            self.pos = start + len + 1;
            // Both ends are ASCII bytes of a `str`: character boundaries.
            self.text.get(start..start + len)
        }

        fn word(&mut self, word: &str, value: Json<'a>) -> Option<Json<'a>> {
            let end = self.pos + word.len();
            if self.text.as_bytes().get(self.pos..end)? != word.as_bytes() {
                return None;
            }
            self.pos = end;
            Some(value)
        }

        /// An integer as serde_json reads it: `u64` unless negative. `-0`, leading zeros,
        /// fractions, exponents and long ones are left to serde_json.
        fn integer(&mut self) -> Option<Json<'a>> {
            let negative = self.peek() == Some(b'-');
            let start = self.pos + usize::from(negative);
            let digits = self.text.as_bytes().get(start..)?;
            let len = digits.iter().take_while(|b| b.is_ascii_digit()).count();
            if len == 0 || len > DIGITS || (len > 1 && digits[0] == b'0') {
                return None;
            }
            if let Some(b'.' | b'e' | b'E') = digits.get(len) {
                return None;
            }
            let magnitude = digits[..len]
                .iter()
                .fold(0u64, |n, d| n * 10 + u64::from(d - b'0'));
            self.pos = start + len;
            match (negative, magnitude) {
                (false, n) => Some(Json::Number(n.into())),
                (true, 0) => None,
                // 18 digits fit an `i64`.
                (true, n) => Some(Json::Number((-(n as i64)).into())),
            }
        }
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
    use proptest::prelude::*;

    #[test]
    fn objects_keep_order_and_repeated_keys() {
        let mut arena = Arena::default();
        let j = arena
            .parse(r#"{"b":1,"a":[true,null,"x\"y"],"b":2.5}"#)
            .unwrap();
        let Json::Object(m) = &j else { panic!() };
        let keys: Vec<&str> = m.iter().map(|(k, _)| *k).collect();
        assert_eq!(keys, ["b", "a", "b"]);
        assert_eq!(j.to_string(), r#"{"b":1,"a":[true,null,"x\"y"],"b":2.5}"#);
    }

    #[test]
    fn keys_and_strings_borrow_from_the_text_unless_escaped() {
        let text = r#"{"cmd":"led","n\u006fde":"x\"y"}"#;
        let mut arena = Arena::default();
        let j = arena.parse(text).unwrap();
        let Json::Object(m) = j else { panic!() };
        let in_text = |s: &str| text.as_bytes().as_ptr_range().contains(&s.as_ptr());
        let (cmd, Json::String(led)) = m[0].clone() else {
            panic!()
        };
        assert!((cmd, led) == ("cmd", "led") && in_text(cmd) && in_text(led));
        let (key, Json::String(value)) = m[1].clone() else {
            panic!()
        };
        assert_eq!((key, value), ("node", "x\"y"));
        assert!(!in_text(key) && !in_text(value), "unescaped copies");
    }

    #[test]
    fn the_arena_is_reused_and_a_large_block_given_back() {
        let mut arena = Arena::default();
        arena.parse(r#"{"cmd":"led","color":[1,2,3]}"#).unwrap();
        let small = arena.0.allocated_bytes();
        for _ in 0..1000 {
            arena.parse(r#"{"cmd":"led","color":[1,2,3]}"#).unwrap();
        }
        assert_eq!(
            arena.0.allocated_bytes(),
            small,
            "no growth from parse to parse"
        );
        let big = format!("[{}0]", "0,".repeat(20_000));
        assert!(matches!(arena.parse(&big), Ok(Json::Array(a)) if a.len() == 20_001));
        assert!(arena.0.allocated_bytes() > ARENA_KEEP);
        arena.parse("{}").unwrap();
        assert!(
            arena.0.allocated_bytes() <= ARENA_KEEP,
            "the large block is given back"
        );
    }

    #[test]
    fn quotes_are_cut_to_a_readable_length() {
        let text = "x".repeat(100);
        let long = Json::String(&text);
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

    /// serde_json's tree for `text`, bypassing the single pass.
    fn by_serde<'a>(text: &'a str, arena: &'a Bump) -> Option<Json<'a>> {
        let mut de = serde_json::Deserializer::from_str(text);
        let value = Seed(arena).deserialize(&mut de).ok()?;
        de.end().ok()?;
        Some(value)
    }

    #[test]
    fn commands_take_the_single_pass() {
        let bump = Bump::new();
        for text in [
            r##"{"cmd":"led","node":"111","color":"#ff0000","brightness":255,"request_id":"r1"}"##,
            r#" { "cmd" : "buzzer", "node" : "all", "pattern" : [ 1 , 0 , -2 ] , "on" : true } "#,
            r#"{"cmd":"led","node":"2","color":[255,0,0],"ttl_ms":500,"user":null,"x":{"y":false}}"#,
            "{}",
            "[]",
            "\"näme\"",
        ] {
            let fast = fast::parse(text, &bump);
            assert!(fast.is_some(), "{text}");
            assert_eq!(fast, by_serde(text, &bump), "{text}");
        }
        for text in [
            r#"{"a":"x\"y"}"#,
            r#"{"a":1.5}"#,
            r#"{"a":1e3}"#,
            r#"{"a":-0}"#,
            r#"{"a":0123}"#,
            r#"{"a":1234567890123456789}"#,
            r#"{"a":"tab	in"}"#,
            r#"{"a":1,}"#,
            r#"{"a" 1}"#,
            r#"{"a":tru}"#,
            "{} x",
            "",
        ] {
            assert_eq!(fast::parse(text, &bump), None, "{text}");
        }
        let deep = format!("{}1{}", "[".repeat(20), "]".repeat(20));
        assert_eq!(
            fast::parse(&deep, &bump),
            None,
            "deep nesting is serde_json's"
        );
        assert!(Arena::default().parse(&deep).is_ok());
    }

    /// JSON-like text: valid values with odd spacing, numbers of every form, strings with escapes
    /// and non-ASCII, nested a few levels; then cut or spliced at random, so that most of the
    /// invalid forms appear too.
    fn json_like() -> impl Strategy<Value = String> {
        let leaf = prop_oneof![
            Just("null".to_owned()),
            Just("true".to_owned()),
            Just("false".to_owned()),
            any::<i64>().prop_map(|n| n.to_string()),
            any::<u64>().prop_map(|n| n.to_string()),
            "-?[0-9]{1,4}(\\.[0-9]{1,2})?([eE][+-]?[0-9])?",
            "\"([a-z#é ]|\\\\n|\\\\\"|\\\\u00e9|\t){0,6}\"",
        ];
        let value = leaf.prop_recursive(4, 24, 4, |inner| {
            prop_oneof![
                prop::collection::vec(inner.clone(), 0..4)
                    .prop_map(|v| format!("[{}]", v.join(","))),
                prop::collection::vec(("[a-z_]{1,3}", inner, "[ \n]{0,2}"), 0..4).prop_map(|m| {
                    let members: Vec<String> = m
                        .iter()
                        .map(|(k, v, ws)| format!("{ws}\"{k}\"{ws}:{ws}{v}"))
                        .collect();
                    format!("{{{}}}", members.join(","))
                }),
            ]
        });
        (
            value,
            any::<prop::sample::Index>(),
            0..3usize,
            "[\\]\\[{}\",:0-9a-z -]{0,2}",
        )
            .prop_map(|(text, at, how, splice)| {
                let cut = at.index(text.len() + 1);
                let cut = (0..=cut)
                    .rev()
                    .find(|&i| text.is_char_boundary(i))
                    .unwrap_or(0);
                match how {
                    0 => text,
                    1 => text[..cut].to_owned(),
                    _ => format!("{}{splice}{}", &text[..cut], &text[cut..]),
                }
            })
    }

    proptest! {
        // Cheap cases, and a disagreement may hide in a rare form: many of them.
        #![proptest_config(ProptestConfig::with_cases(8192))]
        #[test]
        fn the_single_pass_agrees_with_serde_json(text in json_like()) {
            let bump = Bump::new();
            if let Some(fast) = fast::parse(&text, &bump) {
                prop_assert_eq!(Some(fast), by_serde(&text, &bump));
            }
        }
    }

    #[test]
    fn nesting_is_limited_not_a_crash() {
        assert!(Arena::default().parse(&"[".repeat(100_000)).is_err());
        assert!(Arena::default().parse("{} x").is_err(), "trailing text");
    }
}
