//! The island as `IslandControl`'s properties show it: every element from its state document (the
//! JSON the gateway publishes on `ihex/node/<id>/state`), and the dockings they report. No I/O: the
//! server's model task feeds it the documents and events of the core's feed.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use serde::Deserialize;
use serde_json::Value;

/// One element, as the `Elements` property shows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Element {
    /// Node ID in hex.
    pub id: String,
    /// `static`, `mobile` or `unknown`.
    pub role: String,
    /// Answering health checks.
    pub online: bool,
    /// Firmware version, empty until read back.
    pub firmware: String,
    /// The board's unique ID, empty until read back.
    pub uid: String,
    /// The light, as the feature describes it; empty until known.
    pub light: String,
    /// The relay (false until known).
    pub relay: bool,
    /// Its docking connections: (its port, peer, peer's port).
    pub links: Vec<(i64, String, i64)>,
}

/// A docking connection: a mobile element on a static element's port.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Docking {
    /// The static element.
    pub static_element: String,
    /// Its dock port.
    pub port: i64,
    /// The mobile element.
    pub mobile_element: String,
    /// The mobile element's port.
    pub mobile_port: i64,
}

/// The parts of a state document the properties show, read in place: a document is parsed once
/// per change of any node, so nothing else in it is built.
#[derive(Deserialize)]
struct StateDoc<'a> {
    #[serde(borrow)]
    id: Cow<'a, str>,
    #[serde(borrow, default)]
    role: Option<Cow<'a, str>>,
    #[serde(default)]
    online: Option<bool>,
    #[serde(borrow, default)]
    firmware: Option<Firmware<'a>>,
    #[serde(borrow, default)]
    uid: Option<Cow<'a, str>>,
    #[serde(borrow, default)]
    led: Option<Led<'a>>,
    #[serde(default)]
    relay: Option<bool>,
    #[serde(borrow, default)]
    connections: Option<Vec<Link<'a>>>,
}

#[derive(Deserialize)]
struct Firmware<'a> {
    #[serde(borrow, default)]
    version: Option<Cow<'a, str>>,
}

#[derive(Deserialize)]
struct Led<'a> {
    #[serde(borrow, default)]
    mode: Option<Cow<'a, str>>,
    #[serde(borrow, default)]
    color: Option<Cow<'a, str>>,
    #[serde(default)]
    brightness: Option<i64>,
    #[serde(default)]
    period_ms: Option<i64>,
    #[serde(default)]
    duty: Option<i64>,
}

#[derive(Deserialize)]
struct Link<'a> {
    port: i64,
    #[serde(borrow)]
    peer: Cow<'a, str>,
    peer_port: i64,
}

/// The `payload` of a `node_forgotten` event.
#[derive(Deserialize)]
struct Forgotten<'a> {
    #[serde(borrow)]
    payload: ForgottenNode<'a>,
}

#[derive(Deserialize)]
struct ForgottenNode<'a> {
    #[serde(borrow)]
    id: Cow<'a, str>,
}

impl Element {
    /// The element a state document describes.
    fn from_doc(doc: StateDoc<'_>) -> Element {
        let text = |v: Option<Cow<'_, str>>| v.map(Cow::into_owned).unwrap_or_default();
        let light = match doc.led {
            Some(led) => {
                let color = led.color.as_deref().unwrap_or_default();
                let brightness = led.brightness.unwrap_or_default();
                match led.mode.as_deref() {
                    Some("steady") => format!("steady {color} {brightness}"),
                    Some("blink") => format!(
                        "blink {color} {brightness} {} {}",
                        led.period_ms.unwrap_or_default(),
                        led.duty.unwrap_or_default()
                    ),
                    Some(mode) => mode.to_owned(),
                    None => String::new(),
                }
            }
            None => String::new(),
        };
        let links = doc
            .connections
            .unwrap_or_default()
            .into_iter()
            .map(|c| (c.port, c.peer.into_owned(), c.peer_port))
            .collect();
        Element {
            id: doc.id.into_owned(),
            role: doc
                .role
                .map_or_else(|| "unknown".to_owned(), Cow::into_owned),
            online: doc.online.unwrap_or(false),
            firmware: text(doc.firmware.and_then(|f| f.version)),
            uid: text(doc.uid),
            light,
            relay: doc.relay.unwrap_or(false),
            links,
        }
    }

    /// The `Docking` field: `port:peer:peer_port`, separated by commas.
    pub fn docking_text(&self) -> String {
        let parts: Vec<String> = self
            .links
            .iter()
            .map(|(p, peer, pp)| format!("{p}:{peer}:{pp}"))
            .collect();
        parts.join(",")
    }
}

/// Every known element, by node ID. Elements are shared with the properties' values (a change
/// of one element copies the others' handles, not their text), and the dockings are derived again
/// only after a change of links, roles or the elements known.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Island {
    elements: BTreeMap<String, Arc<Element>>,
    dockings_changed: bool,
}

impl Island {
    /// Starts again from a whole view of the island (every node's state document).
    pub fn handle_snapshot<'a>(&mut self, docs: impl IntoIterator<Item = &'a Value>) {
        self.elements = docs
            .into_iter()
            // A document without an `id`, or with a field of another type than the gateway
            // publishes, describes no element.
            .filter_map(|d| StateDoc::deserialize(d).ok())
            .map(Element::from_doc)
            .map(|e| (e.id.clone(), Arc::new(e)))
            .collect();
        self.dockings_changed = true;
    }

    /// A state document as published; true when it changed what the properties show.
    pub fn handle_state(&mut self, json: &str) -> bool {
        let Ok(doc) = serde_json::from_str::<StateDoc<'_>>(json) else {
            return false;
        };
        let e = Element::from_doc(doc);
        match self.elements.get(&e.id) {
            Some(old) if **old == e => return false,
            Some(old) if old.links == e.links && old.role == e.role => {}
            // A new element's role may turn a docking its peer reported.
            _ => self.dockings_changed = true,
        }
        self.elements.insert(e.id.clone(), Arc::new(e));
        true
    }

    /// A `node_forgotten` event as published; true when it removed a known element.
    pub fn handle_forgotten(&mut self, json: &str) -> bool {
        let removed = serde_json::from_str::<Forgotten<'_>>(json)
            .is_ok_and(|f| self.elements.remove(f.payload.id.as_ref()).is_some());
        self.dockings_changed |= removed;
        removed
    }

    /// The elements, by node ID.
    pub fn elements(&self) -> Vec<Arc<Element>> {
        self.elements.values().cloned().collect()
    }

    /// True once after every change that may have changed [`Island::dockings`].
    pub fn take_dockings_changed(&mut self) -> bool {
        std::mem::take(&mut self.dockings_changed)
    }

    /// The dockings, as either side reports them (a connection both report is listed once).
    pub fn dockings(&self) -> Vec<Docking> {
        let mut all = BTreeSet::new();
        for e in self.elements.values() {
            for (port, peer, peer_port) in &e.links {
                let peer_role = self.elements.get(peer).map(|p| p.role.as_str());
                let d = if e.role == "mobile" || peer_role == Some("static") {
                    Docking {
                        static_element: peer.clone(),
                        port: *peer_port,
                        mobile_element: e.id.clone(),
                        mobile_port: *port,
                    }
                } else {
                    Docking {
                        static_element: e.id.clone(),
                        port: *port,
                        mobile_element: peer.clone(),
                        mobile_port: *peer_port,
                    }
                };
                all.insert(d);
            }
        }
        all.into_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const STATIC: &str = r##"{"id":"111","online":true,"role":"static","ports":6,"version":"1.3",
        "firmware":{"version":"0.1.0","trial":false,"image_hash":"3fa2c41b09d8e7"},"uid":"0123456789abcdef01234567",
        "led":{"mode":"blink","color":"#ff0000","brightness":255,"period_ms":500,"duty":50},
        "buzzer":{"mode":"off"},"relay":true,"loops":[3],
        "connections":[{"port":3,"peer":"2","peer_port":0}],"reported":null,"last_seen_ms":120,"first_seen_ms":41000}"##;
    const MOBILE: &str = r#"{"id":"2","online":true,"role":"mobile","led":null,"relay":null,
        "connections":[{"port":0,"peer":"111","peer_port":3}]}"#;

    #[test]
    fn state_documents_become_elements_and_dockings() {
        let mut island = Island::default();
        assert!(island.handle_state(STATIC));
        assert!(!island.handle_state(STATIC), "the same document again");
        assert!(island.handle_state(MOBILE));
        let e = island.elements();
        assert_eq!(e.len(), 2);
        assert_eq!(e[0].id, "111");
        assert_eq!(e[0].light, "blink #ff0000 255 500 50");
        assert_eq!(e[0].firmware, "0.1.0");
        assert_eq!(e[0].docking_text(), "3:2:0");
        assert!(e[0].relay);
        assert_eq!((e[1].role.as_str(), e[1].light.as_str()), ("mobile", ""));
        let d = Docking {
            static_element: "111".into(),
            port: 3,
            mobile_element: "2".into(),
            mobile_port: 0,
        };
        assert_eq!(island.dockings(), vec![d], "reported by both, listed once");
        assert!(island.take_dockings_changed());
        assert!(!island.take_dockings_changed(), "once per change");
        // Another colour: the element changed, its links and role did not.
        let green = STATIC.replace("#ff0000", "#00ff00");
        assert!(island.handle_state(&green));
        assert_eq!(island.elements()[0].light, "blink #00ff00 255 500 50");
        assert!(!island.take_dockings_changed());
        let undocked = STATIC.replace(r#"[{"port":3,"peer":"2","peer_port":0}]"#, "[]");
        assert!(island.handle_state(&undocked));
        let mobile_undocked = MOBILE.replace(r#"[{"port":0,"peer":"111","peer_port":3}]"#, "[]");
        assert!(island.handle_state(&mobile_undocked));
        assert!(island.take_dockings_changed());
        assert_eq!(island.dockings(), vec![]);
        assert!(island.handle_forgotten(
            r#"{"event":"node_forgotten","payload":{"id":"2","reason":"forget","new_id":null}}"#
        ));
        assert_eq!(island.elements().len(), 1);
        assert!(island.take_dockings_changed(), "an element forgotten");
        assert!(!island.handle_state("not json"));
        // Escaped text is read as well as plain text.
        assert!(island.handle_state(r#"{"id":"3","role":"mobile","uid":"a\"b"}"#));
        assert_eq!(island.elements()[1].uid, "a\"b");
        // A field of another type than the gateway publishes: no element.
        assert!(!island.handle_state(r#"{"id":"4","online":"yes"}"#));
        assert_eq!(island.elements().len(), 2);
    }
}
