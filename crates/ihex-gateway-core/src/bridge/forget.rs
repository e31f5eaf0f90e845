//! Forgetting a node: the `forget` command (a lost node only) and a board that now answers under
//! another ID. The node leaves the registry; its docking connections end (`connection_removed`);
//! its retained state document and Home Assistant device are emptied; `node_forgotten` tells
//! everyone. A node heard again afterwards is new (`node_online` with `first_seen: true`).

use std::time::Instant;

use ihex_proto::{NodeId, Uid};

use super::{Bridge, Publication};
use crate::command::CommandError;
use crate::event::{CommandResult, Event, HexId, NodeForgotten, Outcome, Target};
use crate::topic::Topic;

impl Bridge {
    /// `forget` of `id`: refused for an unknown or online node, else done and answered `ok` at
    /// once (no frame is sent).
    pub(super) fn forget_command(&mut self, request_id: Option<String>, id: NodeId, now: Instant) {
        let Some(entry) = self.registry.get(id) else {
            let known = self.registry.known_list();
            let error = CommandError::UnknownNode {
                id: HexId(id),
                known,
            };
            return self.reject(request_id, error);
        };
        if entry.online {
            return self.reject(request_id, CommandError::ForgetOnline(HexId(id)));
        }
        self.forget(id, None, now);
        self.out.emit(Event::CommandResult(CommandResult {
            request_id,
            cmd: "forget".into(),
            node: Target::Node(id),
            result: Outcome::Ok,
            reason: None,
            acked: None,
            refused: None,
            missing: None,
            origin: self.origin_for_answer(),
        }));
    }

    /// The board `uid` answers as `id` now: any other ID it had is forgotten (renumbered).
    pub(super) fn learn_uid(&mut self, id: NodeId, uid: Uid, now: Instant) {
        for old in self.registry.learn_uid(id, uid) {
            tracing::info!(%old, new = %id, "board renumbered: forgetting its old id");
            self.forget(old, Some(id), now);
        }
        // The device's serial number is the UID: its Home Assistant config may have changed.
        self.refresh_ha(id, now);
    }

    /// Drops `id` everywhere; `renumbered_to`: the ID the same board answers to now.
    fn forget(&mut self, id: NodeId, renumbered_to: Option<NodeId>, now: Instant) {
        let steps = self.docking.forget(id, now);
        self.apply(steps, now);
        self.registry.remove(id);
        if let Some(ha) = &mut self.ha {
            for topic in ha.on_forgotten(id) {
                self.out
                    .publish
                    .push_kept(Publication::Cleared(Topic::Ha(topic)));
            }
        }
        self.out
            .publish
            .push_kept(Publication::Cleared(Topic::NodeState(id)));
        self.out.emit(Event::NodeForgotten(NodeForgotten {
            id: HexId(id),
            reason: if renumbered_to.is_some() {
                "renumbered"
            } else {
                "forget"
            }
            .into(),
            new_id: renumbered_to.map(HexId),
        }));
        // The other ends of its connections changed.
        self.finish_input(now);
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use crate::topic::Topic;
    use ihex_proto::{AckResult, Message, Packet};
    use serde_json::json;

    /// 111 and 2 known, then 2 went lost (the health rounds after `with_nodes`' went unanswered).
    fn with_2_lost() -> (Bridge, Instant) {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        for n in 1..=3u8 {
            let t = t0 + S * u32::from(n);
            b.handle_timeout(t);
            b.handle_packet(Packet::report(id(0x111), reply(n, 0)), t + MS);
        }
        b.handle_timeout(t0 + S * 4);
        let out = drain(&mut b);
        assert_eq!(out.one("node_lost")["id"], "2");
        (b, t0 + S * 4)
    }

    #[test]
    fn forget_of_a_lost_node_empties_its_retained_state_and_answers_ok() {
        let (mut b, t) = with_2_lost();
        b.handle_command(
            json!({"cmd": "forget", "node": "2", "request_id": "f"})
                .to_string()
                .as_bytes(),
            t,
        );
        let mut kinds = Vec::new();
        while let Some(p) = b.poll_publication() {
            kinds.push((p.topic(), p.retain(), p.to_json()));
        }
        assert_eq!(
            kinds[0],
            (Topic::NodeState(id(2)), true, String::new()),
            "{kinds:?}"
        );
        let events: Vec<serde_json::Value> = kinds[1..]
            .iter()
            .map(|(_, _, j)| serde_json::from_str(j).unwrap())
            .collect();
        assert_eq!(
            events,
            [
                json!({"event": "node_forgotten", "payload": {"id": "2", "reason": "forget", "new_id": null}}),
                json!({"event": "command_result", "payload": {"request_id": "f", "cmd": "forget",
                        "node": "2", "result": "ok", "reason": null}}),
            ]
        );
        assert!(b.registry().get(id(2)).is_none());
        assert!(b.poll_transmit(t).is_none(), "forget sends nothing");
        // Heard again, it is new.
        b.handle_packet(Packet::report(id(2), reply(9, 0)), t + S);
        let out = drain(&mut b);
        assert_eq!(out.one("node_online")["first_seen"], true);
    }

    #[test]
    fn forget_refuses_online_unknown_and_all() {
        let (mut b, t) = with_2_lost();
        for (cmd, reason) in [
            (
                json!({"cmd": "forget", "node": "111"}),
                "forget: node 111 is online; only a lost node can be forgotten (an online one \
                 would be registered again at its next health reply)",
            ),
            (
                json!({"cmd": "forget", "node": "5"}),
                "unknown node 5; known: 2, 111",
            ),
            (
                json!({"cmd": "forget", "node": "all"}),
                "forget: `node` must be a node id in hex, \"1\" to \"ffd\"; got \"all\"",
            ),
        ] {
            let out = command(&mut b, cmd.clone(), t);
            assert_eq!(out.one("command_rejected")["reason"], reason, "{cmd}");
            assert!(out.states.is_empty());
        }
        assert!(b.registry().get(id(2)).is_some());
    }

    #[test]
    fn forgetting_a_lost_static_element_ends_its_connections() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        dock(&mut b, 0x111, 3, 2, t0);
        // 111 falls silent; 2 keeps answering (it is powered by 111's relay).
        for n in 1..=3u8 {
            let t = t0 + S * u32::from(n);
            b.handle_timeout(t);
            b.handle_packet(Packet::report(id(2), reply(n, 0x01)), t + MS);
        }
        b.handle_timeout(t0 + S * 4);
        assert_eq!(drain(&mut b).one("node_lost")["id"], "111");
        assert_eq!(
            b.connections().len(),
            1,
            "a lost static element keeps its connections"
        );
        let out = command(&mut b, json!({"cmd": "forget", "node": "111"}), t0 + S * 4);
        assert_eq!(
            out.one("connection_removed"),
            &json!({"n": {"id": "2", "port": 0}, "n-1": {"id": "111", "port": 3}})
        );
        assert!(b.connections().is_empty());
        assert_eq!(out.one("command_result")["result"], "ok");
        // 2's document no longer lists the connection.
        let s2 = out.states.iter().find(|(n, _)| *n == id(2)).unwrap();
        assert_eq!(s2.1["connections"], json!([]));
    }

    #[test]
    fn a_board_assigned_a_new_id_forgets_its_old_one() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let uid = "00112233445566778899aabb";
        // First assign: the board becomes 5 (the gateway did not know which board 2 was).
        let commit_seq = |out: Out| {
            out.sent
                .iter()
                .find_map(|p| match p.msg {
                    Message::AssignCommit { seq, .. } => Some(seq),
                    _ => None,
                })
                .unwrap()
        };
        let assign_reply = |seq, new_id| Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail: [0x88, 0x99, 0xaa, 0xbb],
        };
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": uid, "new_id": "5"}),
            t0,
        );
        let seq = commit_seq(out);
        b.handle_packet(Packet::report(id(5), assign_reply(seq, id(5))), t0 + MS);
        let out = drain(&mut b);
        assert!(
            out.named("node_forgotten").is_empty(),
            "2's board is unknown"
        );
        assert_eq!(out.one("command_result")["result"], "ok");
        // Second assign of the same board: 5 is forgotten, 7 stays.
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": uid, "new_id": "7"}),
            t0 + S,
        );
        let seq = commit_seq(out);
        b.handle_packet(Packet::report(id(7), assign_reply(seq, id(7))), t0 + S + MS);
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_forgotten"),
            &json!({"id": "5", "reason": "renumbered", "new_id": "7"})
        );
        assert!(b.registry().get(id(5)).is_none());
        assert!(b.registry().get(id(7)).is_some());
        assert!(
            b.registry().get(id(2)).is_some(),
            "2 is another board as far as anyone knows"
        );
    }
}
