//! Node-ID configuration: the UART request/reply protocol and CAN assignment by unique ID.

use ihex_proto::{
    uart::{UartReply, UartRequest},
    AckResult, Message, NodeId, Packet, Seq,
};

use super::{Node, Output, UART_IDLE_RESET_MS};
use crate::Millis;

impl Node {
    /// One configuration-UART byte (timers already advanced).
    pub(super) fn on_uart_byte(&mut self, byte: u8, now: Millis) {
        // Also without a tick in between: an idle gap drops a half-received request.
        if self.uart.is_pending() && now.since(self.uart_last) >= UART_IDLE_RESET_MS {
            self.uart.reset();
        }
        self.uart_last = now;
        let reply = match self.uart.push(byte) {
            None => return,
            Some(Ok(UartRequest::SetId(id))) => {
                self.take_id(id, true);
                UartReply::Id(id)
            }
            Some(Ok(UartRequest::Query)) => {
                UartReply::Id(self.config.node_id.unwrap_or(NodeId::UNCONFIGURED))
            }
            Some(Err(e)) => UartReply::Error(e),
        };
        // The set-ID reply goes after StoreId/FiltersChanged but before the re-announcement.
        self.queue.push(Output::Uart(reply.encode()));
        self.flush_announce(now);
    }

    /// `AssignSelect`: select ourselves if the UID head is ours, deselect otherwise.
    pub(super) fn on_assign_select(&mut self, uid_head: [u8; 8]) {
        self.selected = uid_head == self.config.uid.head();
    }

    /// `AssignCommit`: the selected node whose UID tail matches takes the ID and replies from it.
    pub(super) fn on_assign_commit(
        &mut self,
        uid_tail: [u8; 4],
        new_id: NodeId,
        seq: Seq,
        now: Millis,
    ) {
        if !self.selected || uid_tail != self.config.uid.tail() {
            self.selected = false;
            return;
        }
        self.take_id(new_id, false);
        let reply = Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail,
        };
        self.queue
            .push(Output::Frame(Packet::report(new_id, reply)));
        self.flush_announce(now);
    }

    /// Puts `id` in force: asks the adapter to store it and to refilter, and remembers whether a
    /// re-announcement is due (it was unconfigured or had another ID).
    fn take_id(&mut self, id: NodeId, from_uart: bool) {
        self.announce_due = self.config.node_id != Some(id);
        self.config.node_id = Some(id);
        self.store_from_uart = from_uart;
        self.queue.push(Output::StoreId(id));
        self.queue.push(Output::FiltersChanged);
    }

    /// Queues the (re)announcement decided by [`Node::take_id`], if any.
    fn flush_announce(&mut self, now: Millis) {
        if core::mem::take(&mut self.announce_due) {
            self.announce(now);
        }
    }
}
