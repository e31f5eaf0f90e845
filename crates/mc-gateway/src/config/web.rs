//! The island view's settings (`http`, `http_token` and `layout` of the options table), checked at
//! start-up whether or not this build has the `web` feature, and the rule that decides who may use
//! its controls.

use std::{
    collections::BTreeMap,
    fmt,
    net::{IpAddr, Ipv4Addr, SocketAddr},
};

use ihex_proto::NodeId;

use super::Settings;
use crate::error::ConfigError;

/// Where the island view listens unless told otherwise: loopback only, so a fresh gateway shows
/// its page to the person at the machine and to nobody else.
pub const DEFAULT_HTTP: SocketAddr = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), 8080);

/// The value of `--http` that switches the view off.
pub const HTTP_OFF: &str = "off";

/// The longest accepted token, in characters.
pub const MAX_TOKEN_LEN: usize = 256;

/// Axial coordinates of a static element's hexagon in the island view (`q` to the right, `r` down
/// and to the left; docs/web.md draws them).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
pub struct Hex {
    /// Column.
    pub q: i32,
    /// Row (slanted).
    pub r: i32,
}

impl fmt::Display for Hex {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{},{}", self.q, self.r)
    }
}

/// Positions of static elements, by node ID.
pub type Layout = BTreeMap<NodeId, Hex>;

/// Who may use the view's controls (`POST /api/command`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Controls {
    /// Anyone who reaches the page: it listens on a loopback address and no token is set.
    Open,
    /// Requests carrying the configured bearer token.
    Token,
    /// Nobody: a non-loopback address without a token (the lab network must not drive relays).
    ReadOnly,
}

/// The island view's checked settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WebConfig {
    /// Where the view listens; `None` when it is off.
    pub listen: Option<SocketAddr>,
    /// The address was configured (flag, variable or file) rather than defaulted: then failing to
    /// listen there stops the gateway; a taken default port only switches the view off.
    pub configured: bool,
    /// Bearer token that unlocks the controls.
    pub token: Option<String>,
    /// Configured positions of static elements.
    pub layout: Layout,
}

impl WebConfig {
    /// The view's part of the resolved options.
    pub fn from_settings(s: &Settings) -> Result<WebConfig, ConfigError> {
        let listen = match s.http.as_deref().map(str::trim) {
            None => Some(DEFAULT_HTTP),
            Some(HTTP_OFF) => None,
            Some(addr) => Some(addr.parse::<SocketAddr>().map_err(|_| {
                ConfigError::invalid(
                    "http",
                    format!(
                        "{addr:?} is not ADDR:PORT (e.g. 127.0.0.1:8080, [::]:8080) or {HTTP_OFF}"
                    ),
                )
            })?),
        };
        let token = match &s.http_token {
            None => None,
            Some(_) if listen.is_none() => {
                return Err(ConfigError::invalid(
                    "http-token",
                    format!("given with --http {HTTP_OFF}"),
                ))
            }
            Some(t) => Some(check_token(t)?),
        };
        let layout = match &s.layout {
            Some(text) => parse_layout(text).map_err(|e| ConfigError::invalid("layout", e))?,
            None => Layout::new(),
        };
        Ok(WebConfig {
            listen,
            configured: s.http.is_some(),
            token,
            layout,
        })
    }

    /// Who may use the controls of a view listening on `bound`.
    pub fn controls(&self, bound: SocketAddr) -> Controls {
        match (&self.token, bound.ip().is_loopback()) {
            (Some(_), _) => Controls::Token,
            (None, true) => Controls::Open,
            (None, false) => Controls::ReadOnly,
        }
    }
}

/// A token goes into an HTTP header: 1 to [`MAX_TOKEN_LEN`] visible ASCII characters.
fn check_token(t: &str) -> Result<String, ConfigError> {
    if t.is_empty() || t.len() > MAX_TOKEN_LEN || !t.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(ConfigError::invalid(
            "http-token",
            format!("must be 1 to {MAX_TOKEN_LEN} visible ASCII characters (no spaces)"),
        ));
    }
    Ok(t.to_owned())
}

/// Parses `ID=Q,R` entries separated by spaces (`111=0,0 112=1,0`): a static element's node ID and
/// the axial coordinates of its hexagon. An ID or a position given twice is refused.
pub fn parse_layout(text: &str) -> Result<Layout, String> {
    let mut layout = Layout::new();
    for entry in text.split_whitespace() {
        let bad = |why: &str| format!("{entry:?}: {why}");
        let (id, pos) = entry
            .split_once('=')
            .ok_or_else(|| bad("expected ID=Q,R (e.g. 111=0,0)"))?;
        let id: NodeId = id.parse().map_err(|e| bad(&format!("{e}")))?;
        if !id.is_sc() {
            return Err(bad("node ID outside 1..=ffd"));
        }
        let (q, r) = pos
            .split_once(',')
            .ok_or_else(|| bad("expected ID=Q,R (e.g. 111=0,0)"))?;
        let coord = |c: &str| {
            c.trim()
                .parse::<i32>()
                .ok()
                .filter(|v| v.abs() <= 1000)
                .ok_or_else(|| bad("coordinates are integers from -1000 to 1000"))
        };
        let hex = Hex {
            q: coord(q)?,
            r: coord(r)?,
        };
        if let Some((other, _)) = layout.iter().find(|(_, h)| **h == hex) {
            return Err(bad(&format!("{hex} is taken by {other}")));
        }
        if layout.insert(id, hex).is_some() {
            return Err(bad(&format!("{id} is placed twice")));
        }
    }
    Ok(layout)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Options;
    use ihex_proto::test_util::id;

    fn web(
        http: Option<&str>,
        token: Option<&str>,
        layout: Option<&str>,
    ) -> Result<WebConfig, ConfigError> {
        let o = Options {
            http: http.map(Into::into),
            http_token: token.map(Into::into),
            layout: layout.map(Into::into),
            ..Options::default()
        };
        WebConfig::from_settings(&o.settings()?)
    }

    #[test]
    fn the_default_is_loopback_8080_and_not_configured() {
        let w = web(None, None, None).unwrap();
        assert_eq!(w.listen, Some("127.0.0.1:8080".parse().unwrap()));
        assert!(!w.configured);
        assert!(w.layout.is_empty());
        let w = web(Some("0.0.0.0:80"), None, None).unwrap();
        assert_eq!(w.listen, Some("0.0.0.0:80".parse().unwrap()));
        assert!(w.configured);
        let w = web(Some("off"), None, None).unwrap();
        assert_eq!(w.listen, None);
        assert!(w.configured);
        assert_eq!(
            web(Some("[::1]:0"), None, None).unwrap().listen,
            Some("[::1]:0".parse().unwrap())
        );
    }

    #[test]
    fn bad_values_name_their_option() {
        for (http, token, layout, field) in [
            (Some("localhost"), None, None, "http"),
            (Some("8080"), None, None, "http"),
            (Some("off"), Some("secret"), None, "http-token"),
            (None, Some("two words"), None, "http-token"),
            (None, Some(""), None, "http-token"),
            (None, None, Some("111"), "layout"),
            (None, None, Some("111=0"), "layout"),
            (None, None, Some("111=a,0"), "layout"),
            (None, None, Some("fff=0,0"), "layout"),
            (None, None, Some("111=0,0 112=0,0"), "layout"),
            (None, None, Some("111=0,0 111=1,0"), "layout"),
            (None, None, Some("111=5000,0"), "layout"),
        ] {
            match web(http, token, layout) {
                Err(ConfigError::Invalid { field: f, reason }) => {
                    assert_eq!(f, field, "{http:?} {token:?} {layout:?}: {reason}")
                }
                other => {
                    panic!("{http:?} {token:?} {layout:?}: expected invalid {field}, got {other:?}")
                }
            }
        }
        let e = web(None, None, Some("111=0,0 112=0,0")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "invalid layout: \"112=0,0\": 0,0 is taken by 111"
        );
    }

    #[test]
    fn layouts_read_ids_as_every_tool_does() {
        let l = parse_layout(" 111=0,0\n0x112=1,-1  A=-2,3 ").unwrap();
        assert_eq!(
            l.into_iter().collect::<Vec<_>>(),
            [
                (id(0xa), Hex { q: -2, r: 3 }),
                (id(0x111), Hex { q: 0, r: 0 }),
                (id(0x112), Hex { q: 1, r: -1 }),
            ]
        );
        assert!(parse_layout("").unwrap().is_empty());
    }

    #[test]
    fn controls_are_open_on_loopback_read_only_elsewhere_unless_a_token_is_set() {
        let open = web(None, None, None).unwrap();
        let token = web(None, Some("s3cret"), None).unwrap();
        for (addr, without, with) in [
            ("127.0.0.1:8080", Controls::Open, Controls::Token),
            ("[::1]:8080", Controls::Open, Controls::Token),
            ("0.0.0.0:8080", Controls::ReadOnly, Controls::Token),
            ("192.168.1.20:8080", Controls::ReadOnly, Controls::Token),
            ("[::]:8080", Controls::ReadOnly, Controls::Token),
        ] {
            let a: SocketAddr = addr.parse().unwrap();
            assert_eq!(open.controls(a), without, "{addr}");
            assert_eq!(token.controls(a), with, "{addr}");
        }
    }
}
