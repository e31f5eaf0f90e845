//! `enum_with_unknown!`: a wire enumeration whose unknown values survive as `Other(u8)`, with its
//! raw-value and name conversions written once (after smoltcp's `src/macros.rs`).

/// Declares a `u8` wire enumeration with an `Other(u8)` arm for values this version does not know,
/// so a newer peer never breaks an older one.
///
/// Each variant is `Name = raw => "snake_name"`. Generated: `KNOWN`, `TABLE`, `to_raw`,
/// `from_raw` (unknown → `Other`), `name` (`None` for `Other`) and `Display` (the snake name, or
/// `other_<n>`), the form the gateway publishes.
macro_rules! enum_with_unknown {
    (
        $(#[$attr:meta])*
        pub enum $name:ident {
            $( $(#[$vattr:meta])* $variant:ident = $raw:literal => $text:literal ),+ $(,)?
        }
    ) => {
        $(#[$attr])*
        #[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub enum $name {
            $( $(#[$vattr])* $variant, )+
            /// A code this version does not know; kept so that newer peers do not break older ones.
            Other(u8),
        }

        impl $name {
            /// Every known value, in wire order.
            pub const KNOWN: &'static [$name] = &[$($name::$variant),+];

            /// Every known wire value with its name, in wire order (the DBC value tables).
            pub const TABLE: &'static [(u8, &'static str)] = &[$(($raw, $text)),+];

            /// Wire value.
            pub const fn to_raw(self) -> u8 {
                match self {
                    $( $name::$variant => $raw, )+
                    $name::Other(v) => v,
                }
            }

            /// From the wire value; unknown values become `Other`.
            pub const fn from_raw(raw: u8) -> Self {
                match raw {
                    $( $raw => $name::$variant, )+
                    v => $name::Other(v),
                }
            }

            /// The snake_case name used in events and logs; `None` for `Other`.
            pub const fn name(self) -> Option<&'static str> {
                match self {
                    $( $name::$variant => Some($text), )+
                    $name::Other(_) => None,
                }
            }
        }

        impl $name {
            /// The snake_case name, or `other_<n>`: what [`Display`] and the events show, without
            /// the formatting machinery (every `BootUp` event carries one).
            ///
            /// [`Display`]: core::fmt::Display
            pub fn text(self) -> &'static str {
                match self.name() {
                    Some(n) => n,
                    None => crate::macros::OTHER_TEXT[usize::from(self.to_raw())],
                }
            }

            /// The value [`text`](Self::text) wrote `s` for.
            pub fn from_text(s: &str) -> Option<Self> {
                match s.strip_prefix("other_") {
                    Some(n) => n.parse().ok().map(Self::from_raw),
                    None => Self::TABLE
                        .iter()
                        .find(|(_, t)| *t == s)
                        .map(|&(raw, _)| Self::from_raw(raw)),
                }
            }
        }

        impl core::fmt::Display for $name {
            /// The snake_case name, or `other_<n>` for a value this version does not know.
            fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                f.write_str(self.text())
            }
        }

        /// As its [`text`](Self::text).
        #[cfg(feature = "serde")]
        impl serde::Serialize for $name {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.serialize_str(self.text())
            }
        }

        /// From its [`text`](Self::text).
        #[cfg(feature = "serde")]
        impl<'de> serde::Deserialize<'de> for $name {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                d.deserialize_str(crate::macros::TextVisitor(Self::from_text, stringify!($name)))
            }
        }
    };
}

/// `other_<n>` for every `n`, built at compile time: the text of a value an enumeration does not
/// know costs a table lookup.
pub(crate) static OTHER_TEXT: [&str; 256] = {
    let mut out = [""; 256];
    let mut n = 0;
    while n < 256 {
        let (bytes, len) = &OTHER_BYTES[n];
        let (text, _) = bytes.split_at(*len);
        out[n] = match core::str::from_utf8(text) {
            Ok(t) => t,
            Err(_) => panic!("other_<n> is ASCII"),
        };
        n += 1;
    }
    out
};

/// The bytes of [`OTHER_TEXT`] and their lengths (`other_255` is the longest).
static OTHER_BYTES: [([u8; 9], usize); 256] = {
    let mut out = [([0; 9], 0); 256];
    let mut n = 0;
    while n < 256 {
        let (buf, len) = &mut out[n];
        let prefix = b"other_";
        let mut i = 0;
        while i < prefix.len() {
            buf[i] = prefix[i];
            i += 1;
        }
        *len = crate::write_decimal(n as u8, buf, i);
        n += 1;
    }
    out
};

/// Reads a wire enumeration from its text with its `from_text`.
#[cfg(feature = "serde")]
pub(crate) struct TextVisitor<T>(pub fn(&str) -> Option<T>, pub &'static str);

#[cfg(feature = "serde")]
impl<T> serde::de::Visitor<'_> for TextVisitor<T> {
    type Value = T;

    fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "a {} name or other_<0-255>", self.1)
    }

    fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<T, E> {
        (self.0)(s).ok_or_else(|| E::invalid_value(serde::de::Unexpected::Str(s), &self))
    }
}
