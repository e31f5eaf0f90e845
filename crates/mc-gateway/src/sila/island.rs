//! The island as `IslandControl`'s properties show it: every element from its state document (the
//! JSON the gateway publishes on `ihex/node/<id>/state`), and the dockings they report. No I/O: the
//! server's model task feeds it the documents and events of the core's feed.

use std::collections::{BTreeMap, BTreeSet};

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

impl Element {
    /// The element a state document describes; `None` for a document without an `id`.
    pub fn from_state(doc: &Value) -> Option<Element> {
        let text = |v: Option<&Value>| v.and_then(Value::as_str).unwrap_or_default().to_owned();
        let id = doc.get("id")?.as_str()?.to_owned();
        let light = match doc.get("led") {
            Some(led) if led.is_object() => {
                let int = |k: &str| led.get(k).and_then(Value::as_i64).unwrap_or_default();
                match led.get("mode").and_then(Value::as_str) {
                    Some("steady") => {
                        format!("steady {} {}", text(led.get("color")), int("brightness"))
                    }
                    Some("blink") => format!(
                        "blink {} {} {} {}",
                        text(led.get("color")),
                        int("brightness"),
                        int("period_ms"),
                        int("duty")
                    ),
                    Some(mode) => mode.to_owned(),
                    None => String::new(),
                }
            }
            _ => String::new(),
        };
        let links = doc
            .get("connections")
            .and_then(Value::as_array)
            .map(|cs| {
                cs.iter()
                    .filter_map(|c| {
                        Some((
                            c.get("port")?.as_i64()?,
                            c.get("peer")?.as_str()?.to_owned(),
                            c.get("peer_port")?.as_i64()?,
                        ))
                    })
                    .collect()
            })
            .unwrap_or_default();
        Some(Element {
            role: doc
                .get("role")
                .and_then(Value::as_str)
                .unwrap_or("unknown")
                .to_owned(),
            online: doc.get("online").and_then(Value::as_bool).unwrap_or(false),
            firmware: text(doc.get("firmware").and_then(|f| f.get("version"))),
            uid: text(doc.get("uid")),
            light,
            relay: doc.get("relay").and_then(Value::as_bool).unwrap_or(false),
            links,
            id,
        })
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

/// Every known element, by node ID.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Island {
    elements: BTreeMap<String, Element>,
}

impl Island {
    /// Starts again from a whole view of the island (every node's state document).
    pub fn handle_snapshot<'a>(&mut self, docs: impl IntoIterator<Item = &'a Value>) {
        self.elements = docs
            .into_iter()
            .filter_map(Element::from_state)
            .map(|e| (e.id.clone(), e))
            .collect();
    }

    /// A state document as published; true when it changed what the properties show.
    pub fn handle_state(&mut self, json: &str) -> bool {
        let Some(e) = serde_json::from_str(json)
            .ok()
            .as_ref()
            .and_then(Element::from_state)
        else {
            return false;
        };
        if self.elements.get(&e.id) == Some(&e) {
            return false;
        }
        self.elements.insert(e.id.clone(), e);
        true
    }

    /// An event as published; true when it changed what the properties show (`node_forgotten`).
    pub fn handle_event(&mut self, json: &str) -> bool {
        let Ok(v) = serde_json::from_str::<Value>(json) else {
            return false;
        };
        if v.get("event").and_then(Value::as_str) != Some("node_forgotten") {
            return false;
        }
        let id = v
            .get("payload")
            .and_then(|p| p.get("id"))
            .and_then(Value::as_str);
        id.is_some_and(|id| self.elements.remove(id).is_some())
    }

    /// The elements, by node ID.
    pub fn elements(&self) -> Vec<Element> {
        self.elements.values().cloned().collect()
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
        let undocked = STATIC.replace(r#"[{"port":3,"peer":"2","peer_port":0}]"#, "[]");
        assert!(island.handle_state(&undocked));
        let mobile_undocked = MOBILE.replace(r#"[{"port":0,"peer":"111","peer_port":3}]"#, "[]");
        assert!(island.handle_state(&mobile_undocked));
        assert_eq!(island.dockings(), vec![]);
        assert!(island.handle_event(
            r#"{"event":"node_forgotten","payload":{"id":"2","reason":"forget","new_id":null}}"#
        ));
        assert_eq!(island.elements().len(), 1);
        assert!(!island.handle_state("not json"));
    }
}
