//! The bridge's side of a firmware update: images uploaded over MQTT are checked and kept
//! ([`Uploads`]); `fw_update` takes the uploaded image of that name, else asks the adapter for
//! the file ([`FwLoad`]: the core reads no files); the image is checked, then one [`FwSender`]
//! runs at a time; its frames go out only when the bridge has nothing else to send, and its
//! events are published like every other.

use std::collections::VecDeque;
use std::time::Instant;

use ihex_proto::{FwStatus, NodeId, Packet};

use super::{FwConfig, FwImage, FwSender, Uploads};
use crate::bridge::output::Outputs;
use crate::event::{CommandResult, Event, Outcome, Target};

/// An `fw_update` waiting for its image: the adapter reads `image` from the firmware directory
/// and hands the bytes (or why it could not) to [`crate::Bridge::handle_fw_image`].
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct FwLoad {
    /// The command's `request_id`.
    pub request_id: Option<String>,
    /// The file name (a plain name, checked by the command parser).
    pub image: String,
    /// The nodes, resolved when the command arrived.
    pub nodes: Vec<NodeId>,
    /// Allow a downgrade.
    pub force: bool,
    /// Nodes left out because a lease holds them, with the reason (reported as `skipped`).
    pub skipped: Vec<(NodeId, String)>,
}

/// The update state of the bridge.
#[derive(Debug)]
pub(crate) struct FwUpdates {
    config: FwConfig,
    loads: VecDeque<FwLoad>,
    /// A load was handed to the adapter and not answered yet.
    loading: bool,
    sender: Option<FwSender>,
    /// The last finished update, kept for [`LATE_WINDOW`] after its report: a node it gave up
    /// that reports the new image confirmed gets an `fw_correction`.
    last: Option<(FwSender, Instant)>,
    uploads: Uploads,
}

/// How long after its report an update still corrects a late confirmation.
pub const LATE_WINDOW: std::time::Duration = std::time::Duration::from_secs(600);

impl FwUpdates {
    pub(crate) fn new(config: FwConfig) -> Self {
        FwUpdates {
            config,
            loads: VecDeque::new(),
            loading: false,
            sender: None,
            last: None,
            uploads: Uploads::default(),
        }
    }

    /// An update is loading or running: a second one is refused.
    pub(crate) fn busy(&self) -> bool {
        self.loading || !self.loads.is_empty() || self.sender.is_some()
    }

    /// The elements of the running update not done yet; `None` when no update runs (none, or
    /// one still reading its image).
    pub(crate) fn open_nodes(&self) -> Option<Vec<NodeId>> {
        let s = self.sender.as_ref().filter(|s| !s.is_finished())?;
        Some(s.open_nodes().collect())
    }

    /// An `fw_update`: starts at once with the uploaded image of that name, else asks the
    /// adapter for the file.
    pub(crate) fn request(&mut self, load: FwLoad, now: Instant, out: &mut Outputs) {
        match self.uploads.get(&load.image) {
            Some(image) => {
                let image = Ok(image.bytes().to_vec());
                self.loading = true;
                self.on_image(load, image, now, out);
            }
            None => self.loads.push_back(load),
        }
    }

    /// An image uploaded over MQTT: checked, kept when good, answered either way.
    pub(crate) fn on_upload(
        &mut self,
        name: &str,
        bytes: Vec<u8>,
        retained: bool,
        out: &mut Outputs,
    ) {
        let answer = self
            .uploads
            .receive(name, bytes, retained, self.config.trusted_key.as_ref());
        tracing::info!(
            image = %name,
            result = ?answer.result,
            reason = answer.reason.as_deref().unwrap_or(""),
            "firmware image uploaded"
        );
        out.emit(Event::FwUpload(Box::new(answer)));
    }

    #[must_use]
    pub(crate) fn poll_load(&mut self) -> Option<FwLoad> {
        let load = self.loads.pop_front()?;
        self.loading = true;
        Some(load)
    }

    /// The image file arrived (or not): start the update, or answer why not. Either way the
    /// command gets its one `command_result`.
    pub(crate) fn on_image(
        &mut self,
        load: FwLoad,
        bytes: Result<Vec<u8>, String>,
        now: Instant,
        out: &mut Outputs,
    ) {
        self.loading = false;
        let checked = bytes.and_then(|b| FwImage::check(b).map_err(|e| e.to_string()));
        let (result, reason) = match checked {
            Err(why) => (Outcome::Failed, Some(format!("{}: {why}", load.image))),
            Ok(_) if self.sender.is_some() => (
                Outcome::Failed,
                Some("an update is already running".to_string()),
            ),
            Ok(image) => {
                tracing::info!(
                    image = %load.image,
                    version = %image.version(),
                    nodes = load.nodes.len(),
                    "firmware update starts"
                );
                self.sender = Some(
                    FwSender::new(
                        image,
                        load.nodes.iter().copied(),
                        load.force,
                        load.request_id.clone(),
                        self.config.clone(),
                        now,
                    )
                    .with_skipped(load.skipped.clone()),
                );
                (Outcome::Ok, None)
            }
        };
        out.emit(Event::CommandResult(CommandResult {
            request_id: load.request_id,
            cmd: "fw_update".into(),
            node: match load.nodes.as_slice() {
                [one] => Target::Node(*one),
                _ => Target::All,
            },
            result,
            reason,
            acked: None,
            refused: None,
            missing: None,
            // Answered once the image is read, after the command's turn: the audit trail pairs
            // it with its command by `request_id`.
            origin: None,
        }));
        self.drain(out);
    }

    /// The island's dockings, `(static element, mobile element)`, for the update just started
    /// (see [`FwSender::set_docked`]).
    pub(crate) fn set_docked(&mut self, docked: impl IntoIterator<Item = (NodeId, NodeId)>) {
        if let Some(s) = self.sender.as_mut() {
            s.set_docked(docked);
        }
    }

    pub(crate) fn on_status(&mut self, src: NodeId, st: FwStatus, now: Instant, out: &mut Outputs) {
        if let Some(s) = self.sender.as_mut() {
            s.handle_status(src, st, now);
        }
        self.drain(out);
    }

    /// A node's state report named its firmware: see [`FwSender::handle_firmware`].
    pub(crate) fn on_firmware(
        &mut self,
        src: NodeId,
        version: ihex_proto::FirmwareVersion,
        trial: bool,
        now: Instant,
        out: &mut Outputs,
    ) {
        if let Some(s) = self.sender.as_mut() {
            s.handle_firmware(src, version, trial, now);
        }
        if let Some((s, until)) = self.last.as_mut() {
            if now < *until {
                s.handle_firmware(src, version, trial, now);
                while let Some(e) = s.poll_event() {
                    out.emit(e);
                }
            } else {
                self.last = None;
            }
        }
        self.drain(out);
    }

    pub(crate) fn on_boot_up(
        &mut self,
        src: NodeId,
        reset: ihex_proto::ResetReason,
        now: Instant,
        out: &mut Outputs,
    ) {
        if let Some(s) = self.sender.as_mut() {
            if reset == ihex_proto::ResetReason::PowerOn {
                s.handle_power_on(src, now);
            }
            s.handle_boot_up(src, now);
        }
        self.drain(out);
    }

    pub(crate) fn on_bus(&mut self, down: bool, now: Instant, out: &mut Outputs) {
        if let Some(s) = self.sender.as_mut() {
            if down {
                s.handle_bus_down(now);
            } else {
                s.handle_bus_recovered(now);
            }
        }
        self.drain(out);
    }

    pub(crate) fn tick(&mut self, now: Instant, out: &mut Outputs) {
        if let Some(s) = self.sender.as_mut() {
            s.handle_timeout(now);
        }
        self.drain(out);
    }

    pub(crate) fn cancel(&mut self, reason: &str, now: Instant, out: &mut Outputs) {
        if let Some(s) = self.sender.as_mut() {
            s.cancel(reason, now);
        }
        self.drain(out);
    }

    pub(crate) fn deadline(&self) -> Option<Instant> {
        self.sender.as_ref().and_then(FwSender::poll_timeout)
    }

    #[must_use]
    pub(crate) fn poll_transmit(&mut self) -> Option<Packet> {
        let s = self.sender.as_mut()?;
        let p = s.poll_transmit();
        if s.is_done() && s.poll_event().is_none() {
            self.retire();
        }
        p
    }

    /// Moves the sender's events to the publications; drops a finished sender once its last
    /// frames (an abort) are out.
    fn drain(&mut self, out: &mut Outputs) {
        let Some(s) = self.sender.as_mut() else {
            return;
        };
        while let Some(e) = s.poll_event() {
            out.emit(e);
        }
        if s.is_done() {
            self.retire();
        }
    }

    /// The finished sender stays for late confirmations.
    fn retire(&mut self) {
        if let Some(s) = self.sender.take() {
            let until = s.finished_at().unwrap_or(s.started_at()) + LATE_WINDOW;
            self.last = Some((s, until));
        }
    }
}

#[cfg(test)]
mod tests {
    use ihex_image::{pack, Board, SigningKey};
    use ihex_proto::{FirmwareVersion, FwPhase, FwRefusal, Message, Packet};
    use serde_json::json;

    use super::*;
    use crate::bridge::test_support::{command, drain, id, with_nodes};

    fn image_bytes() -> Vec<u8> {
        let key = SigningKey::from_text(ihex_image::test_key::SECRET_TEXT).unwrap();
        let version = FirmwareVersion {
            major: 1,
            minor: 3,
            patch: 0,
        };
        pack(
            Board::SIM,
            ihex_proto::PROTOCOL_VERSION,
            version,
            &[7; 600],
            &key,
        )
        .unwrap()
    }

    /// The `firmware` of `id`'s last published state document.
    fn firmware_shown(
        out: &crate::bridge::test_support::Out,
        raw: u16,
    ) -> Option<serde_json::Value> {
        out.states
            .iter()
            .rev()
            .find(|(n, _)| *n == id(raw))
            .map(|(_, doc)| doc["firmware"].clone())
    }

    #[test]
    fn a_confirmation_clears_trial_in_the_state_document() {
        use ihex_proto::{BootRole, ResetReason, StateReport};
        let (mut b, t0) = with_nodes(&[0x111]);
        let t = t0 + crate::bridge::test_support::S;
        let version = FirmwareVersion::new(1, 3, 0);
        let boot = Message::BootUp {
            version: ihex_proto::PROTOCOL_VERSION,
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::Software,
        };
        b.handle_packet(Packet::report(id(0x111), boot), t);
        let out = drain(&mut b);
        // Its read-back after the restart: the new image, on trial.
        for q in &out.queries {
            let Message::StateQuery { seq, parts } = q.msg else {
                continue;
            };
            let fw = StateReport::Firmware {
                version,
                trial: true,
            };
            b.handle_packet(Packet::report(id(0x111), Message::StateReport(fw)), t);
            let end = StateReport::End {
                seq,
                parts,
                count: 1,
            };
            b.handle_packet(Packet::report(id(0x111), Message::StateReport(end)), t);
        }
        let out = drain(&mut b);
        assert_eq!(
            firmware_shown(&out, 0x111).expect("a state document")["trial"],
            true
        );
        // It confirms: its next status says idle.
        let idle = FwStatus::phase(FwPhase::Idle, FwRefusal::None);
        b.handle_packet(Packet::report(id(0x111), Message::FwStatus(idle)), t);
        let out = drain(&mut b);
        let shown = firmware_shown(&out, 0x111).expect("the document is republished");
        assert_eq!(shown["trial"], false);
        assert_eq!(shown["version"], "1.3.0");
    }

    #[test]
    fn fw_update_loads_the_image_starts_and_answers_once() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let cmd = json!({"cmd":"fw_update","image":"a.ihex","nodes":"all","request_id":"u1"});
        let out = command(&mut b, cmd.clone(), t0);
        assert!(out.events.is_empty() && out.sent.is_empty());
        let load = b.poll_fw_load().expect("the image is asked for");
        assert_eq!(load.image, "a.ihex");
        assert_eq!(load.nodes, vec![id(2), id(0x111)]);
        // A second update meanwhile is refused.
        let out = command(&mut b, cmd, t0);
        assert!(out.one("command_rejected")["reason"]
            .as_str()
            .unwrap()
            .contains("an update is running"));

        b.handle_fw_image(load, Ok(image_bytes()), t0);
        let out = drain(&mut b);
        let result = out.one("command_result");
        assert_eq!(result["result"], "ok");
        assert_eq!(result["request_id"], "u1");
        // The begins went out, one per node.
        let begins: Vec<_> = out
            .sent
            .iter()
            .filter(|p| matches!(p.msg, Message::FwBegin { .. }))
            .map(|p| p.dest)
            .collect();
        assert_eq!(begins, vec![id(2), id(0x111)]);

        // A command during the update goes out before any more update frames.
        for n in [2, 0x111] {
            let st = FwStatus {
                first_missing: 0,
                run: 32,
                missing: 32,
                ..FwStatus::phase(FwPhase::Header, FwRefusal::None)
            };
            b.handle_packet(Packet::report(id(n), Message::FwStatus(st)), t0);
        }
        b.handle_command(br#"{"cmd":"power","node":"2","on":true}"#, t0);
        let first = b.poll_transmit(t0).unwrap().packet;
        assert!(matches!(first.msg, Message::PowerSet { .. }), "{first:?}");
        let next = b.poll_transmit(t0).unwrap().packet;
        assert!(
            matches!(next.msg, Message::FwData { index: 0, .. }),
            "{next:?}"
        );
        assert_eq!(next.dest, NodeId::BROADCAST);

        // Both refuse: the update ends with one report.
        for n in [2, 0x111] {
            let st = FwStatus::phase(FwPhase::Refused, FwRefusal::WrongBoard);
            b.handle_packet(Packet::report(id(n), Message::FwStatus(st)), t0);
        }
        let out = drain(&mut b);
        let report = out.one("fw_report");
        assert_eq!(report["nodes"][0]["outcome"], "refused");
        assert_eq!(report["nodes"][0]["reason"], "wrong_board");
        assert!(!b.fw_update_running());
    }

    #[test]
    fn update_frames_never_fill_the_transmit_window() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_fw_upload("a.ihex", image_bytes(), false, t0);
        command(
            &mut b,
            json!({"cmd":"fw_update","image":"a.ihex","nodes":"2"}),
            t0,
        );
        let st = FwStatus {
            first_missing: 0,
            run: 32,
            missing: 32,
            ..FwStatus::phase(FwPhase::Header, FwRefusal::None)
        };
        b.handle_packet(Packet::report(id(2), Message::FwStatus(st)), t0);
        // Handed out and never confirmed: the update stops at its part of the window.
        let mut out = 0;
        while let Some(t) = b.poll_transmit(t0) {
            assert!(matches!(t.packet.msg, Message::FwData { .. }), "{t:?}");
            out += 1;
        }
        assert_eq!(out, crate::bridge::FW_WINDOW);
        b.handle_command(br#"{"cmd":"power","node":"2","on":true}"#, t0);
        let t = b.poll_transmit(t0).expect("the command goes out at once");
        assert!(matches!(t.packet.msg, Message::PowerSet { .. }), "{t:?}");
    }

    #[test]
    fn a_bad_or_missing_image_fails_the_command_with_the_reason() {
        let (mut b, t0) = with_nodes(&[2]);
        for (bytes, says) in [
            (Err("no such file".to_string()), "no such file"),
            (Ok(image_bytes()[..700].to_vec()), "truncated"),
        ] {
            command(
                &mut b,
                json!({"cmd":"fw_update","image":"x.ihex","nodes":"2"}),
                t0,
            );
            let load = b.poll_fw_load().unwrap();
            b.handle_fw_image(load, bytes, t0);
            let out = drain(&mut b);
            let r = out.one("command_result");
            assert_eq!(r["result"], "failed");
            assert!(r["reason"].as_str().unwrap().contains(says), "{r}");
            assert!(out.sent.is_empty());
            assert!(!b.fw_update_running());
        }
    }

    #[test]
    fn an_uploaded_image_is_answered_and_used_without_reading_a_file() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_fw_upload("up.ihex", image_bytes()[..900].to_vec(), false, t0);
        let out = drain(&mut b);
        let a = out.one("fw_upload");
        assert_eq!(a["result"], "rejected");
        assert!(a["reason"].as_str().unwrap().contains("truncated"), "{a}");

        b.handle_fw_upload("up.ihex", image_bytes(), false, t0);
        let out = drain(&mut b);
        let a = out.one("fw_upload");
        assert_eq!(
            (a["name"].as_str(), a["result"].as_str()),
            (Some("up.ihex"), Some("stored"))
        );
        assert_eq!(a["version"], "1.3.0");
        assert_eq!(a["signature"], "unchecked");

        let cmd = json!({"cmd":"fw_update","image":"up.ihex","nodes":"2","request_id":"u"});
        let out = command(&mut b, cmd, t0);
        assert!(b.poll_fw_load().is_none(), "no file is asked for");
        assert_eq!(out.one("command_result")["result"], "ok");
        assert!(out
            .sent
            .iter()
            .any(|p| matches!(p.msg, Message::FwBegin { .. }) && p.dest == id(2)));
        assert!(b.fw_update_running());
    }

    #[test]
    fn unknown_nodes_are_rejected() {
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(
            &mut b,
            json!({"cmd":"fw_update","image":"x.ihex","nodes":"2,5"}),
            t0,
        );
        assert!(out.one("command_rejected")["reason"]
            .as_str()
            .unwrap()
            .starts_with("unknown node 5"));
        assert!(b.poll_fw_load().is_none());
    }

    #[test]
    fn fw_cancel_stops_the_update_and_answers_once() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let out = command(&mut b, json!({"cmd":"fw_cancel","request_id":"c0"}), t0);
        assert_eq!(
            out.one("command_rejected")["reason"],
            "fw_cancel: no firmware update is running (the fw_report of the last one says how it ended)"
        );
        // While the image file is read, nothing is sent yet: asked to try again.
        command(
            &mut b,
            json!({"cmd":"fw_update","image":"f.ihex","nodes":"2"}),
            t0,
        );
        let load = b.poll_fw_load().unwrap();
        let out = command(&mut b, json!({"cmd":"fw_cancel","request_id":"c1"}), t0);
        assert!(out.one("command_rejected")["reason"]
            .as_str()
            .unwrap()
            .starts_with("fw_cancel: the update is still reading its image"));
        b.handle_fw_image(load, Err("no such file".into()), t0);
        drain(&mut b);

        b.handle_fw_upload("up.ihex", image_bytes(), false, t0);
        drain(&mut b);
        let cmd = json!({"cmd":"fw_update","image":"up.ihex","nodes":"2,111","request_id":"u"});
        assert_eq!(
            command(&mut b, cmd, t0).one("command_result")["result"],
            "ok"
        );
        let out = command(&mut b, json!({"cmd":"fw_cancel","request_id":"c2"}), t0);
        let result = out.one("command_result");
        assert_eq!(
            (&result["cmd"], &result["result"], &result["request_id"]),
            (&json!("fw_cancel"), &json!("ok"), &json!("c2"))
        );
        let report = out.one("fw_report");
        assert_eq!(report["request_id"], "u", "the update's report");
        for n in report["nodes"].as_array().unwrap() {
            assert_eq!(
                (&n["outcome"], &n["reason"]),
                (&json!("failed"), &json!(crate::bridge::FW_CANCELLED)),
                "{report}"
            );
        }
        // The nodes were told to drop the transfer.
        let aborts: Vec<_> = out
            .sent
            .iter()
            .filter(|p| {
                matches!(
                    p.msg,
                    Message::FwEnd {
                        action: ihex_proto::FwAction::Abort,
                        ..
                    }
                )
            })
            .map(|p| p.dest)
            .collect();
        assert_eq!(aborts, vec![id(2), id(0x111)]);
        assert!(!b.fw_update_running());
        let out = command(&mut b, json!({"cmd":"fw_cancel","request_id":"c3"}), t0);
        assert_eq!(out.one("command_rejected")["request_id"], "c3");
    }

    #[test]
    fn fw_cancel_honours_leases_on_the_updates_elements() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let out = command(
            &mut b,
            json!({"cmd":"lease","owner":"run-42","nodes":"111","seconds":60}),
            t0,
        );
        let token = out.one("lease_granted")["token"]
            .as_str()
            .unwrap()
            .to_owned();
        b.handle_fw_upload("up.ihex", image_bytes(), false, t0);
        drain(&mut b);
        let cmd = json!({"cmd":"fw_update","image":"up.ihex","nodes":"2,111","lease":token});
        assert_eq!(
            command(&mut b, cmd, t0).one("command_result")["result"],
            "ok"
        );
        // Someone without the token may not stop the leased element's update.
        let out = command(&mut b, json!({"cmd":"fw_cancel"}), t0);
        assert!(out.one("command_rejected")["reason"]
            .as_str()
            .unwrap()
            .starts_with("111 is leased by run-42"));
        assert!(b.fw_update_running());
        let out = command(&mut b, json!({"cmd":"fw_cancel","lease":token}), t0);
        assert_eq!(out.one("command_result")["result"], "ok");
        assert_eq!(out.one("fw_report")["nodes"].as_array().unwrap().len(), 2);
    }
}
