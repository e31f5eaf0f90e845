//! The island as `IslandControl`'s properties show it: every element from its state document (as
//! the gateway publishes it on `ihex/node/<id>/state`), and the dockings they report. No I/O: the
//! server's model task feeds it the documents and events of the core's feed.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use ihex_gateway_core::event::{NodeState, Role};
use serde::Deserialize;

/// One element, as the `Elements` property shows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Element {
    /// Node ID in hex.
    pub id: String,
    /// Static or mobile, when the element has told.
    pub role: Option<Role>,
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
    /// `static`, `mobile` or `unknown`, as the `Elements` property shows it.
    pub fn role_name(&self) -> &'static str {
        self.role.map_or("unknown", Role::name)
    }

    /// The element a state document describes.
    fn from_state(doc: &NodeState) -> Element {
        let light = match &doc.led {
            Some(led) => {
                let color = led.color.as_deref().unwrap_or_default();
                let brightness = led.brightness.unwrap_or_default();
                match &*led.mode {
                    "steady" => format!("steady {color} {brightness}"),
                    "blink" => format!(
                        "blink {color} {brightness} {} {}",
                        led.period_ms.unwrap_or_default(),
                        led.duty.unwrap_or_default()
                    ),
                    mode => mode.to_owned(),
                }
            }
            None => String::new(),
        };
        let links = doc
            .connections
            .iter()
            .map(|c| (c.port.into(), c.peer.0.to_string(), c.peer_port.into()))
            .collect();
        Element {
            id: doc.id.0.to_string(),
            role: doc.role,
            online: doc.online,
            firmware: doc
                .firmware
                .as_ref()
                .map(|f| f.version.clone())
                .unwrap_or_default(),
            uid: doc.uid.clone().unwrap_or_default(),
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
    pub fn handle_snapshot<'a>(&mut self, docs: impl IntoIterator<Item = &'a NodeState>) {
        self.elements = docs
            .into_iter()
            .map(Element::from_state)
            .map(|e| (e.id.clone(), Arc::new(e)))
            .collect();
        self.dockings_changed = true;
    }

    /// A state document as published; true when it changed what the properties show.
    pub fn handle_state(&mut self, doc: &NodeState) -> bool {
        let e = Element::from_state(doc);
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
                let peer_role = self.elements.get(peer).and_then(|p| p.role);
                let d = if e.role == Some(Role::Mobile) || peer_role == Some(Role::Static) {
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
    const MOBILE: &str = r#"{"id":"2","online":true,"role":"mobile","ports":1,"version":null,
        "firmware":null,"uid":null,"led":null,"buzzer":null,"relay":null,"loops":[],
        "connections":[{"port":0,"peer":"111","peer_port":3}],"reported":null,"last_seen_ms":0,"first_seen_ms":0}"#;

    /// The document a JSON text (as the gateway publishes it) describes.
    fn doc(json: &str) -> NodeState {
        serde_json::from_str(json).unwrap()
    }

    #[test]
    fn state_documents_become_elements_and_dockings() {
        let mut island = Island::default();
        assert!(island.handle_state(&doc(STATIC)));
        assert!(
            !island.handle_state(&doc(STATIC)),
            "the same document again"
        );
        assert!(island.handle_state(&doc(MOBILE)));
        let e = island.elements();
        assert_eq!(e.len(), 2);
        assert_eq!(e[0].id, "111");
        assert_eq!(e[0].light, "blink #ff0000 255 500 50");
        assert_eq!(e[0].firmware, "0.1.0");
        assert_eq!(e[0].uid, "0123456789abcdef01234567");
        assert_eq!(e[0].docking_text(), "3:2:0");
        assert!(e[0].relay);
        assert_eq!((e[1].role_name(), e[1].light.as_str()), ("mobile", ""));
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
        assert!(island.handle_state(&doc(&green)));
        assert_eq!(island.elements()[0].light, "blink #00ff00 255 500 50");
        assert!(!island.take_dockings_changed());
        let steady = STATIC.replace(
            r##"{"mode":"blink","color":"#ff0000","brightness":255,"period_ms":500,"duty":50}"##,
            r##"{"mode":"steady","color":"#0000ff","brightness":7}"##,
        );
        assert!(island.handle_state(&doc(&steady)));
        assert_eq!(island.elements()[0].light, "steady #0000ff 7");
        let undocked = STATIC.replace(r#"[{"port":3,"peer":"2","peer_port":0}]"#, "[]");
        assert!(island.handle_state(&doc(&undocked)));
        let mobile_undocked = MOBILE.replace(r#"[{"port":0,"peer":"111","peer_port":3}]"#, "[]");
        assert!(island.handle_state(&doc(&mobile_undocked)));
        assert!(island.take_dockings_changed());
        assert_eq!(island.dockings(), vec![]);
        assert!(island.handle_forgotten(
            r#"{"event":"node_forgotten","payload":{"id":"2","reason":"forget","new_id":null}}"#
        ));
        assert_eq!(island.elements().len(), 1);
        assert!(island.take_dockings_changed(), "an element forgotten");
        assert!(!island.handle_forgotten("not json"));
        // A node the gateway knows nothing about yet.
        let bare = MOBILE.replace(r#""role":"mobile""#, r#""role":null"#);
        assert!(island.handle_state(&doc(&bare.replace(r#""id":"2""#, r#""id":"7ff""#))));
        let e = island.elements();
        assert_eq!((e[1].id.as_str(), e[1].role_name()), ("7ff", "unknown"));
    }
}
