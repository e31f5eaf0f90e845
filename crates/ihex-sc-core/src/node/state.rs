//! State read-back: the reports answering a `StateQuery`, in the order the protocol fixes.

use ihex_proto::{
    BootRole, DockState, Message, Port, PowerState, Seq, StateParts, StateReport, PROTOCOL_VERSION,
};

use super::Node;
use crate::Millis;

/// Most reports one reply carries before its `End`: LED, buzzer, power, a dock report per port
/// and the five identity parts.
const MAX_REPORTS: usize = 3 + Port::COUNT as usize + 5;

impl Node {
    /// `StateQuery`: one report per part of the groups asked that this node knows, in ascending
    /// part number, then `End` echoing `seq` with the groups answered and the count sent.
    pub(super) fn on_state_query(&mut self, seq: Seq, parts: StateParts, now: Millis) {
        let answered = parts.known();
        let reports = self.state_reports(answered, now);
        for r in &reports {
            self.report(Message::StateReport(*r));
        }
        self.report(Message::StateReport(StateReport::End {
            seq,
            parts: answered,
            // At most `MAX_REPORTS`, far below 256.
            count: reports.len() as u8,
        }));
    }

    /// The reports for `parts` at `now`, without the closing `End`.
    fn state_reports(
        &self,
        parts: StateParts,
        now: Millis,
    ) -> heapless::Vec<StateReport, MAX_REPORTS> {
        let mut out = heapless::Vec::new();
        // `MAX_REPORTS` is sized for every group at once, so no push can fail.
        let mut push = |r| {
            let _ = out.push(r);
        };
        if parts.contains(StateParts::ACTUATORS) {
            push(StateReport::Led(self.led));
            push(StateReport::Buzzer(self.buzzer));
            push(StateReport::Power(PowerState {
                relay: self.relay,
                loops: self.loops(),
                confirmed: self.confirmed,
                identify_s: self.identify_remaining_s(now),
                role: self.config.role,
                ports: self.config.ports,
            }));
        }
        if parts.contains(StateParts::DOCKING) && self.config.role == BootRole::Static {
            let loops = self.loops();
            for port in (0..self.config.ports).filter_map(Port::new) {
                let state = DockState {
                    closed: loops & port.mask() != 0,
                    confirmed: self.confirmed & port.mask() != 0,
                    partner: self.links[port.get() as usize],
                };
                if state.closed || state.confirmed || state.partner.is_some() {
                    push(StateReport::Dock { port, state });
                }
            }
        }
        if parts.contains(StateParts::IDENTITY) {
            let fw = self.config.firmware;
            push(StateReport::Firmware {
                version: fw.version,
                trial: fw.trial,
            });
            push(StateReport::ImageHash(fw.image_hash));
            push(StateReport::UidLow(self.config.uid.low()));
            push(StateReport::UidHigh(self.config.uid.high()));
            push(StateReport::Protocol {
                version: PROTOCOL_VERSION,
            });
        }
        out
    }

    /// Whole seconds of identify left, rounded up (an identify lasts at most 255 s).
    fn identify_remaining_s(&self, now: Millis) -> u8 {
        self.identify_until.map_or(0, |until| {
            let s = until.since(now).div_ceil(1000);
            s.min(u64::from(u8::MAX)) as u8
        })
    }
}
