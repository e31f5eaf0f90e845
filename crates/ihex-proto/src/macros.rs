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

        impl core::fmt::Display for $name {
            /// The snake_case name, or `other_<n>` for a value this version does not know.
            fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                match self.name() {
                    Some(n) => f.write_str(n),
                    None => write!(f, "other_{}", self.to_raw()),
                }
            }
        }
    };
}
