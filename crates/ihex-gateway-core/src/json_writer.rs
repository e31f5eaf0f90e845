//! The JSON text of the publications every answered command makes — its `command_result`, the
//! node's state document and, with Home Assistant discovery, its light's state — written by hand: the same bytes serde_json writes from their
//! `Serialize` derives (the MQTT API, docs/mqtt-api.md), in fewer and larger writes. serde_json
//! escapes every key and writes each piece separately, which was a third of an answered command's
//! instructions (callgrind); here the keys and punctuation between two values are one literal,
//! strings are scanned once and escaped only where they need it, and numbers go through `itoa`.
//! The tests compare every field and awkward strings with serde_json's output, so the two cannot
//! drift apart.

use bytes::{BufMut, BytesMut};

use crate::event::{
    hex_digits, BuzzerState, CommandResult, Firmware, HexId, LedState, Link, NodeState, Outcome,
    Refusal, Reported, Target,
};
use crate::ha::{light::RgbColor, LightState};
use crate::origin::Origin;

/// Appends `{"event":"command_result","payload":…}`, as [`crate::event::write_json`] of
/// `Event::CommandResult(r)` does.
pub(crate) fn write_command_result(r: &CommandResult, out: &mut BytesMut) {
    // Every field named: one added to the type must be added here too.
    let CommandResult {
        request_id,
        cmd,
        node,
        result,
        reason,
        acked,
        refused,
        missing,
        origin,
    } = r;
    let mut w = Writer(out);
    w.raw(b"{\"event\":\"command_result\",\"payload\":{\"request_id\":");
    w.opt_str(request_id.as_deref());
    w.raw(b",\"cmd\":");
    w.str(cmd);
    w.raw(b",\"node\":");
    match node {
        Target::Node(id) => w.id(HexId(*id)),
        Target::All => w.raw(b"\"all\""),
    }
    w.raw(match result {
        Outcome::Ok => b",\"result\":\"ok\",\"reason\":",
        Outcome::Refused => b",\"result\":\"refused\",\"reason\":",
        Outcome::Timeout => b",\"result\":\"timeout\",\"reason\":",
        Outcome::Failed => b",\"result\":\"failed\",\"reason\":",
        Outcome::Expired => b",\"result\":\"expired\",\"reason\":",
    });
    w.opt_str(reason.as_deref());
    if let Some(acked) = acked {
        w.raw(b",\"acked\":");
        w.ids(acked);
    }
    if let Some(refused) = refused {
        w.raw(b",\"refused\":[");
        for (i, Refusal { id, reason }) in refused.iter().enumerate() {
            w.raw(if i == 0 { b"{\"id\":" } else { b",{\"id\":" });
            w.id(*id);
            w.raw(b",\"reason\":");
            w.str(reason);
            w.raw(b"}");
        }
        w.raw(b"]");
    }
    if let Some(missing) = missing {
        w.raw(b",\"missing\":");
        w.ids(missing);
    }
    if let Some(origin) = origin {
        w.raw(b",\"origin\":");
        w.origin(origin);
    }
    w.raw(b"}}");
}

/// Appends a node's state document, as [`crate::event::write_json`] of it does.
pub(crate) fn write_node_state(s: &NodeState, out: &mut BytesMut) {
    // Every field named: one added to the type must be added here too.
    let NodeState {
        id,
        online,
        role,
        ports,
        version,
        firmware,
        uid,
        led,
        buzzer,
        relay,
        loops,
        connections,
        reported,
        last_seen_ms,
        first_seen_ms,
    } = s;
    let mut w = Writer(out);
    w.raw(b"{\"id\":");
    w.id(*id);
    w.raw(if *online {
        b",\"online\":true,\"role\":"
    } else {
        b",\"online\":false,\"role\":"
    });
    match role {
        None => w.raw(b"null"),
        Some(r) => w.plain_str(r.name()),
    }
    w.raw(b",\"ports\":");
    w.opt_u64(ports.map(u64::from));
    w.raw(b",\"version\":");
    match version {
        Some(v) => w.plain(v.digits(&mut [0; 7])),
        None => w.null(),
    }
    w.raw(b",\"firmware\":");
    match firmware {
        Some(Firmware {
            version,
            trial,
            image_hash,
        }) => {
            w.raw(b"{\"version\":");
            w.str(version);
            w.raw(if *trial {
                b",\"trial\":true,\"image_hash\":"
            } else {
                b",\"trial\":false,\"image_hash\":"
            });
            w.str(image_hash);
            w.raw(b"}");
        }
        None => w.null(),
    }
    w.raw(b",\"uid\":");
    w.opt_str(uid.as_deref());
    w.raw(b",\"led\":");
    match led {
        Some(led) => w.led(led),
        None => w.null(),
    }
    w.raw(b",\"buzzer\":");
    match buzzer {
        Some(buzzer) => w.buzzer(buzzer),
        None => w.null(),
    }
    w.raw(b",\"relay\":");
    w.opt_bool(*relay);
    w.raw(b",\"loops\":[");
    for (i, port) in loops.iter().enumerate() {
        if i > 0 {
            w.raw(b",");
        }
        w.u64(u64::from(*port));
    }
    w.raw(b"],\"connections\":[");
    for (i, link) in connections.iter().enumerate() {
        let Link {
            port,
            peer,
            peer_port,
        } = link;
        w.raw(if i == 0 {
            b"{\"port\":"
        } else {
            b",{\"port\":"
        });
        w.u64(u64::from(*port));
        w.raw(b",\"peer\":");
        w.id(*peer);
        w.raw(b",\"peer_port\":");
        w.u64(u64::from(*peer_port));
        w.raw(b"}");
    }
    w.raw(b"],\"reported\":");
    match reported {
        Some(r) => w.reported(r),
        None => w.null(),
    }
    w.raw(b",\"last_seen_ms\":");
    w.u64(*last_seen_ms);
    w.raw(b",\"first_seen_ms\":");
    w.u64(*first_seen_ms);
    w.raw(b"}");
}

/// Appends a Home Assistant light's state, as [`crate::event::write_json`] of `s` does.
pub(crate) fn write_light_state(s: &LightState, out: &mut BytesMut) {
    let LightState {
        state,
        color_mode,
        color,
        brightness,
        effect,
    } = s;
    let mut w = Writer(out);
    w.raw(b"{\"state\":");
    w.opt_str(state.as_deref());
    if let Some(mode) = color_mode {
        w.raw(b",\"color_mode\":");
        w.str(mode);
    }
    if let Some(RgbColor { r, g, b }) = color {
        w.raw(b",\"color\":{\"r\":");
        w.u64((*r).into());
        w.raw(b",\"g\":");
        w.u64((*g).into());
        w.raw(b",\"b\":");
        w.u64((*b).into());
        w.raw(b"}");
    }
    w.member_u64(b",\"brightness\":", brightness.map(Into::into));
    if let Some(effect) = effect {
        w.raw(b",\"effect\":");
        w.str(effect);
    }
    w.raw(b"}");
}

/// Appends pieces of JSON text to the publication's buffer.
struct Writer<'a>(&'a mut BytesMut);

impl Writer<'_> {
    /// Literal JSON text: keys, punctuation, `true`, names that need no escaping.
    fn raw(&mut self, text: &[u8]) {
        self.0.extend_from_slice(text);
    }

    fn null(&mut self) {
        self.raw(b"null");
    }

    /// A string, escaped as serde_json escapes it ([`crate::json_text::write_str`]).
    fn str(&mut self, s: &str) {
        self.0.reserve(s.len() + 2);
        crate::json_text::write_str(s, |t| self.0.extend_from_slice(t.as_bytes()));
    }

    /// A string known to need no escaping, in quotes.
    fn plain_str(&mut self, s: &str) {
        self.plain(s.as_bytes());
    }

    /// [`Writer::plain_str`] of text as bytes.
    fn plain(&mut self, text: &[u8]) {
        self.0.reserve(text.len() + 2);
        self.0.put_u8(b'"');
        self.0.extend_from_slice(text);
        self.0.put_u8(b'"');
    }

    fn opt_str(&mut self, s: Option<&str>) {
        match s {
            Some(s) => self.str(s),
            None => self.null(),
        }
    }

    fn id(&mut self, id: HexId) {
        self.plain(hex_digits(id.0, &mut [0; 4]));
    }

    fn ids(&mut self, ids: &[HexId]) {
        self.raw(b"[");
        for (i, id) in ids.iter().enumerate() {
            if i > 0 {
                self.raw(b",");
            }
            self.id(*id);
        }
        self.raw(b"]");
    }

    fn u64(&mut self, n: u64) {
        self.raw(itoa::Buffer::new().format(n).as_bytes());
    }

    fn opt_u64(&mut self, n: Option<u64>) {
        match n {
            Some(n) => self.u64(n),
            None => self.null(),
        }
    }

    fn bool(&mut self, b: bool) {
        self.raw(if b { b"true" } else { b"false" });
    }

    fn opt_bool(&mut self, b: Option<bool>) {
        match b {
            Some(b) => self.bool(b),
            None => self.null(),
        }
    }

    /// An object's optional number member (`skip_serializing_if = "Option::is_none"`): `key`
    /// is the comma, the quoted key and the colon.
    fn member_u64(&mut self, key: &[u8], n: Option<u64>) {
        if let Some(n) = n {
            self.raw(key);
            self.u64(n);
        }
    }

    fn led(&mut self, led: &LedState) {
        let LedState {
            mode,
            color,
            brightness,
            period_ms,
            duty,
        } = led;
        self.raw(b"{\"mode\":");
        self.str(mode);
        if let Some(color) = color {
            self.raw(b",\"color\":");
            self.str(color);
        }
        self.member_u64(b",\"brightness\":", brightness.map(u64::from));
        self.member_u64(b",\"period_ms\":", period_ms.map(u64::from));
        self.member_u64(b",\"duty\":", duty.map(u64::from));
        self.raw(b"}");
    }

    fn buzzer(&mut self, buzzer: &BuzzerState) {
        let BuzzerState {
            mode,
            freq_hz,
            on_ms,
            off_ms,
            count,
        } = buzzer;
        self.raw(b"{\"mode\":");
        self.str(mode);
        self.member_u64(b",\"freq_hz\":", freq_hz.map(u64::from));
        self.member_u64(b",\"on_ms\":", on_ms.map(u64::from));
        self.member_u64(b",\"off_ms\":", off_ms.map(u64::from));
        self.member_u64(b",\"count\":", count.map(u64::from));
        self.raw(b"}");
    }

    fn reported(&mut self, r: &Reported) {
        let Reported {
            relay,
            led_on,
            led_blink,
            buzzer,
            identify,
            error_passive,
            tec,
            rec,
            uptime_s,
        } = r;
        self.raw(b"{\"relay\":");
        self.bool(*relay);
        self.raw(b",\"led_on\":");
        self.bool(*led_on);
        self.raw(b",\"led_blink\":");
        self.bool(*led_blink);
        self.raw(b",\"buzzer\":");
        self.bool(*buzzer);
        self.raw(b",\"identify\":");
        self.bool(*identify);
        self.raw(b",\"error_passive\":");
        self.bool(*error_passive);
        self.raw(b",\"tec\":");
        self.u64(u64::from(*tec));
        self.raw(b",\"rec\":");
        self.u64(u64::from(*rec));
        self.raw(b",\"uptime_s\":");
        self.u64(u64::from(*uptime_s));
        self.raw(b"}");
    }

    fn origin(&mut self, o: &Origin) {
        let Origin {
            interface,
            user,
            claimed,
        } = o;
        self.raw(b"{\"interface\":");
        self.plain_str(interface.as_str());
        if let Some(user) = user {
            self.raw(b",\"user\":");
            self.str(user);
        }
        if let Some(claimed) = claimed {
            self.raw(b",\"claimed\":");
            self.str(claimed);
        }
        self.raw(b"}");
    }
}

#[cfg(test)]
mod tests {
    use ihex_proto::test_util::id;
    use ihex_proto::{BuzzerCommand, LedCommand, Rgb};
    use proptest::prelude::*;

    use super::*;
    use crate::event::{Event, Role, Version};
    use crate::origin::Interface;
    use crate::Publication;

    /// Strings that need escaping, or look as if they might.
    const AWKWARD: [&str; 10] = [
        "",
        "plain",
        "quote \" inside",
        "back\\slash and /slash",
        "\u{0}\u{1}\u{7}\u{8}\u{9}\u{a}\u{b}\u{c}\u{d}\u{e}\u{1b}\u{1f} controls",
        "\"",
        "\\",
        "del \u{7f} and U+2028 \u{2028}",
        "Grüße, 漢字, 🙂",
        "\n",
    ];

    /// What serde_json writes for the event or document, and what is published.
    fn both(p: Publication) -> (String, String) {
        let serde = match &p {
            Publication::Event(e) => serde_json::to_string(e),
            Publication::State(s) => serde_json::to_string(s),
            other => panic!("{other:?}"),
        }
        .unwrap();
        (serde, p.to_json())
    }

    fn result(n: usize) -> CommandResult {
        let text = |k: usize| AWKWARD[(n + k) % AWKWARD.len()].to_owned();
        CommandResult {
            request_id: (!n.is_multiple_of(3)).then(|| text(0)),
            cmd: text(1).into(),
            node: if n.is_multiple_of(4) {
                Target::All
            } else {
                Target::Node(id(n as u16 % 0x7ff + 1))
            },
            result: [
                Outcome::Ok,
                Outcome::Refused,
                Outcome::Timeout,
                Outcome::Failed,
                Outcome::Expired,
            ][n % 5],
            reason: n.is_multiple_of(2).then(|| text(2)),
            acked: (n % 3 == 1).then(|| (0..n % 4).map(|i| HexId(id(i as u16 + 1))).collect()),
            refused: (n % 5 == 2).then(|| {
                (0..n % 3)
                    .map(|i| Refusal {
                        id: HexId(id(0x100 + i as u16)),
                        reason: text(i + 3),
                    })
                    .collect()
            }),
            missing: (n % 7 > 3).then(|| vec![HexId(id(0x7ff)), HexId(id(0x10))]),
            origin: (!n.is_multiple_of(6)).then(|| Origin {
                interface: Interface::ALL[n % Interface::ALL.len()],
                user: (n % 2 == 1).then(|| text(4)),
                claimed: (n % 3 == 2).then(|| text(5)),
            }),
        }
    }

    fn state(n: usize) -> NodeState {
        let text = |k: usize| AWKWARD[(n + k) % AWKWARD.len()].to_owned();
        let led = [
            LedCommand::Off,
            LedCommand::Steady {
                color: Rgb::new(0x12, 0xab, 0xff),
                brightness: 200,
            },
            LedCommand::Blink {
                color: Rgb::new(0, 0, 1),
                brightness: 0,
                period_10ms: 255,
                duty_pct: 50,
            },
        ];
        let buzzer = [
            BuzzerCommand::Off,
            BuzzerCommand::Continuous { freq_hz: 440 },
            BuzzerCommand::Pattern {
                freq_hz: 65535,
                on_10ms: 1,
                off_10ms: 255,
                count: 0,
            },
        ];
        let mut led = led.map(|c| Some(LedState::from(c))).to_vec();
        led.push(None);
        led.push(Some(LedState {
            mode: text(0).into(),
            color: Some(text(1)),
            brightness: None,
            period_ms: Some(u16::MAX),
            duty: None,
        }));
        let mut buzzer = buzzer.map(|c| Some(BuzzerState::from(c))).to_vec();
        buzzer.push(None);
        NodeState {
            id: HexId(id(n as u16 % 0x7ff + 1)),
            online: n.is_multiple_of(2),
            role: [None, Some(Role::Static), Some(Role::Mobile)][n % 3],
            ports: (!n.is_multiple_of(4)).then_some(n as u8),
            version: (n % 3 != 1).then_some(Version(n as u8, 255 - n as u8)),
            firmware: (n % 2 == 1).then(|| Firmware {
                version: text(2),
                trial: n % 4 == 1,
                image_hash: "00ff".repeat(n % 5),
            }),
            uid: n.is_multiple_of(3).then(|| text(3)),
            led: led[n % led.len()].clone(),
            buzzer: buzzer[n % buzzer.len()].clone(),
            relay: [None, Some(true), Some(false)][n % 3],
            loops: (0..8).filter(|p| (n >> p) & 1 == 1).collect(),
            connections: (0..n % 4)
                .map(|i| Link {
                    port: i as u8,
                    peer: HexId(id(0x111 + i as u16)),
                    peer_port: 5 - i as u8,
                })
                .collect(),
            reported: n.is_multiple_of(2).then_some(Reported {
                relay: n.is_multiple_of(4),
                led_on: n.is_multiple_of(3),
                led_blink: true,
                buzzer: false,
                identify: n.is_multiple_of(5),
                error_passive: n.is_multiple_of(6),
                tec: n as u8,
                rec: 255,
                uptime_s: u32::MAX - n as u32,
            }),
            last_seen_ms: [0, 1, 999, u64::MAX][n % 4],
            first_seen_ms: 10u64.pow((n % 20) as u32),
        }
    }

    #[test]
    fn command_results_are_the_bytes_serde_json_writes() {
        for n in 0..420 {
            let (serde, ours) = both(Publication::Event(Event::CommandResult(result(n))));
            assert_eq!(ours, serde, "case {n}");
        }
    }

    #[test]
    fn state_documents_are_the_bytes_serde_json_writes() {
        for n in 0..420 {
            let (serde, ours) = both(Publication::State(state(n)));
            assert_eq!(ours, serde, "case {n}");
        }
    }

    #[test]
    fn light_states_are_the_bytes_serde_json_writes() {
        let leds = [
            None,
            Some(LedCommand::Off),
            Some(LedCommand::Steady {
                color: Rgb::new(0, 128, 255),
                brightness: 0,
            }),
            Some(LedCommand::Blink {
                color: Rgb::new(255, 9, 10),
                brightness: 255,
                period_10ms: 1,
                duty_pct: 99,
            }),
        ];
        let mut states: Vec<LightState> = leds.into_iter().map(LightState::from_led).collect();
        for (n, text) in AWKWARD.iter().enumerate() {
            states.push(LightState {
                state: (n % 2 == 0).then(|| text.to_string().into()),
                color_mode: Some(text.to_string().into()),
                color: None,
                brightness: (n % 3 == 0).then_some(n as u8),
                effect: Some(text.to_string().into()),
            });
        }
        for (n, s) in states.iter().enumerate() {
            let mut ours = BytesMut::new();
            write_light_state(s, &mut ours);
            let serde = serde_json::to_string(s).unwrap();
            assert_eq!(std::str::from_utf8(&ours).unwrap(), serde, "case {n}");
        }
    }

    proptest! {
        #[test]
        fn any_string_is_escaped_as_serde_json_escapes_it(
            s in any::<String>(),
            ascii in "[\\x00-\\x7f]{0,40}",
        ) {
            let mut r = result(1);
            r.request_id = Some(s.clone());
            r.reason = Some(ascii.clone());
            let (serde, ours) = both(Publication::Event(Event::CommandResult(r)));
            prop_assert_eq!(ours, serde);
            let mut d = state(3);
            d.uid = Some(ascii);
            d.led = Some(LedState { mode: s.into(), color: None, brightness: None, period_ms: None, duty: None });
            let (serde, ours) = both(Publication::State(d));
            prop_assert_eq!(ours, serde);
        }
    }
}
