//! The sub-controller's behaviour, written once as a sans-IO state machine.
//!
//! A [`Node`] takes inputs — received frames, signal-loop levels per dock port, UART bytes, the passage
//! of time — and produces outputs: frames to send, UART replies, a node ID to persist, and the
//! [`Actuators`] setting (LED PWM and blink, buzzer tone and pattern, relay) the hardware must show.
//! It does no I/O and never blocks: the firmware (`sc-fw`) and the simulator (`sim-node`) are thin
//! adapters that feed it and carry out what it asks, so they behave identically by construction.
//! No input can make it panic, and every frame it emits passes `Packet::validate`.
//!
//! # Driving it
//!
//! Call the `handle_*` methods as inputs arrive and [`Node::tick`] at the latest at [`Node::poll_at`]
//! (every `handle_*` also runs the timers that are due, so a late tick only delays, never loses,
//! an event). After every call:
//!
//! 1. if [`Node::actuators_changed`] (true once per change, and on the first call after
//!    [`Node::new`]), apply [`Node::actuators`] — *before* sending, so that the relay is already off
//!    when the `DockRemoved` that goes with it leaves;
//! 2. drain [`Node::poll_output`] until `None` and carry each [`Output`] out in order:
//!    [`Output::Frame`] → transmit; [`Output::Uart`] → write the two bytes; [`Output::StoreId`] →
//!    persist (report failure with [`Node::handle_store_failed`]); [`Output::FiltersChanged`] →
//!    reinstall `ihex_proto::filter::sc_filters(node.node_id())` before sending the frames after it;
//!    the firmware-update outputs ([`Output::EraseDfu`], [`Output::WriteDfu`],
//!    [`Output::HashDfu`], [`Output::MarkUpdated`], [`Output::MarkBooted`], [`Output::Reset`]) as
//!    described under *Firmware update*, reporting each result with its `handle_fw_*` method.
//!
//! Time is [`Millis`] from any monotonic origin; it may stand still, and a clock going backwards is
//! treated as no time passing.
//!
//! # Identity
//!
//! * With an ID (`Config::node_id`, `0x001..=0xFFD`; a reserved stored value counts as none) the node
//!   announces itself at [`Node::new`]: `BootUp { version: PROTOCOL_VERSION, role, ports, reset }`.
//! * Its firmware identity (`Config::firmware`: version, first 7 bytes of the image hash, trial flag)
//!   and UID are the adapter's to supply; the core only reports them (see *State read-back*).
//! * **Unconfigured** (no ID) it sends nothing on the bus and ignores every command — broadcast
//!   ones included — except `AssignSelect` / `AssignCommit`. Its loops are still debounced.
//! * **UART** (`ihex_proto::uart`): bytes go through a `UartDecoder`; a half-received request is
//!   dropped after [`UART_IDLE_RESET_MS`] without bytes. `SetId(id)` → `StoreId(id)`,
//!   `FiltersChanged`, the UART reply `Id(id)`, and — if the node was unconfigured or had another ID
//!   — a new `BootUp` from the new ID (a mobile element also hand-shakes again, see below). The ID is
//!   in force at once, even before the adapter stores it. `Query` → `Id(current)` (`0xFFE` when
//!   none). Bad bytes → `Error(Malformed)`, reserved IDs → `Error(ReservedId)`.
//!   [`Node::handle_store_failed`] → `Fault ConfigStore` (when the node has an ID) and, if the
//!   failed store came from a UART request, the UART reply `Error(StoreFailed)`.
//! * **CAN assignment** (configured nodes too, for renumbering): `AssignSelect { uid_head }` selects
//!   the node whose UID starts so and deselects every other. `AssignCommit { uid_tail, new_id, seq }`
//!   to a selected node with that UID tail → `StoreId`, `FiltersChanged`, `AssignReply { seq, Ok,
//!   new_id, uid_tail }` sent *from `new_id`*, then `BootUp` if the ID changed. The node stays
//!   selected, so a repeated commit (lost reply) is answered again. A commit with another tail
//!   deselects silently.
//!
//! # Commands
//!
//! Frames are taken only if extended, not remote, and addressed to the node's ID or to broadcast;
//! reports and frames for others are ignored. A frame addressed to the node's own ID that does not
//! decode (unknown kind, wrong length, value out of range, wrong source) is answered with
//! `Fault { BadFrame, arg: kind bits, detail }` where detail byte 0 is the error class (1 unknown
//! kind, 2 length, 3 value, 4 address), byte 1 the data length, bytes 2–3 the bad value (class 3).
//! A bad *broadcast* frame is dropped silently, so that one bad frame does not make every node on
//! the bus answer at once.
//!
//! Every acknowledged command — to the node or broadcast, each node answering for itself — gets
//! `Ack { kind, seq, result, detail }`:
//!
//! | command | effect | refusals |
//! |---|---|---|
//! | `PowerSet { on }` | relay = `on` (the gateway may force it either way) | `Unsupported`: mobile or port-less node |
//! | `LedSet` | LED duty = colour × brightness / 255 per channel; blink → `Some((period_10ms × 10, duty_pct))` | — |
//! | `BuzzerSet` | `Off` / `Tone` / `Pattern` (on/off in ms); a pattern with `count > 0` returns to `Off` after `count × (on + off)` ms, or earlier on [`Node::handle_buzzer_done`] | — |
//! | `Identify { seconds }` | for `seconds` s the LED shows [`IDENTIFY_LED`] and the buzzer [`IDENTIFY_BUZZER`], then the commanded state returns; `0` stops it | — |
//! | `DockConfirm { port }` | the port is confirmed, relay on | `Unsupported` (mobile / port-less); `InvalidValue`, detail 1 (port ≥ `ports`); `InvalidState`, detail 1, **plus** `Fault DockConfirmNotDocked arg=port` (loop open) |
//! | `DockRefuse { port }` | the relay is not switched; a confirmation of that port is withdrawn (relay off if it was the last) and its link forgotten | as `DockConfirm`, except an open loop is fine |
//! | `DockLink { port, partner }` | remembers `partner` (mobile ID and its own port) as docked on `port`; `None` forgets it | `Unsupported` (mobile / port-less); `InvalidValue`, detail 1 (port ≥ `ports`); `InvalidState`, detail 1 (a link for a port that is not confirmed; clearing is always fine) |
//!
//! Values the protocol forbids (blink duty 0, tone 5 Hz, …) never reach this table: they fail to
//! decode and yield `BadFrame`. Commands during an identify change the state that returns after it.
//! `HealthCheck { seq }` (own ID or broadcast) → `HealthReply { seq, flags, loops, tec, rec,
//! uptime_s }`: flags from the *effective* actuators (`RELAY`, `LED_ON` = some channel lit,
//! `LED_BLINK` = lit and blinking, `BUZZER` = not off, `IDENTIFY`), the role (`MOBILE`) and CAN
//! state (`ERROR_PASSIVE`); `loops` is the debounced loop bitmap; uptime in whole seconds since
//! [`Node::new`], saturating at 24 bits.
//!
//! # State read-back
//!
//! `StateQuery { seq, parts }` (own ID or broadcast; not acknowledged) → one `StateReport` per part
//! of the groups asked that this version knows (other bits are ignored), in ascending part
//! number, then `End { seq, parts: answered, count }`:
//!
//! * actuators: `Led` and `Buzzer` — the *commanded* state exactly as `LedSet`/`BuzzerSet` carried
//!   it (an identify does not show here; a finite pattern that has ended is `Off`) — and `Power`:
//!   relay, debounced loop bitmap, confirmed bitmap, identify seconds remaining (rounded up), role,
//!   port count;
//! * docking (static role only): `Dock(port)` for every port that is closed, confirmed or linked,
//!   with its link;
//! * identity: `Firmware` (version, trial flag) and `ImageHash` from `Config::firmware`, `UidLow`,
//!   `UidHigh` from `Config::uid`, and `Protocol` (`PROTOCOL_VERSION`, as in the `BootUp`).
//!
//! A full reply is at most 17 frames, so it always fits the output queue. A query changes nothing.
//!
//! # Signal loops and docking (static role)
//!
//! Levels of ports below `Config::ports` are debounced: a level counts once it has been reported
//! and not contradicted for [`DEBOUNCE_MS`] (a bouncing contact yields one event, `DEBOUNCE_MS` after
//! its last bounce; a glitch shorter than that yields none). Every loop starts open, so a loop
//! closed at reset is reported `DEBOUNCE_MS` after the adapter first reports it — adapters report
//! every port's level right after [`Node::new`]. Levels may be reported on edges, periodically, or
//! both.
//!
//! * closed → `DockDetected { port }`; the relay is **not** switched on.
//! * `DockConfirm` for a closed port → relay on (the port is *confirmed*).
//! * open → if the port was confirmed, it no longer is and — when no other confirmed port is still
//!   docked — the relay goes off in this same call, before `DockRemoved { port }` is queued.
//! * `DockLink` for a confirmed port → the node remembers which mobile element (and its port) the
//!   gateway found docked there and reports it in `Dock(port)`, so a restarted gateway can rebuild
//!   the island's dockings. The link goes when the port opens, when its confirmation is withdrawn
//!   (`DockRefuse`) and at a power cut. Across a reset the node asks for itself (an update's swap
//!   or revert) the adapter keeps the relay, the confirmed ports and their links ([`Retained`],
//!   [`Node::retained`], [`Node::restore`]): the docked mobile element keeps its power, and a
//!   restored port reports no new `DockDetected` — only `DockRemoved` if its loop is not closed
//!   [`DEBOUNCE_MS`] after the restore.
//!
//! The relay is the element's one power relay: it stays on while any confirmed port is docked and
//! goes off when the last one opens. An open port that was never confirmed does not touch it (so a
//! relay forced on by `PowerSet` stays on). The relay switches off on the *debounced* open edge: a
//! glitch shorter than [`DEBOUNCE_MS`] must not power-cycle the mobile element.
//!
//! # Mobile role
//!
//! A mobile element reports no dock events. After boot with an ID (or on getting an ID) it sends
//! `Handshake { port }` once: its own port whose loop debounces closed first, or — if none has
//! within [`HANDSHAKE_SETTLE_MS`] (longer than the debounce, so a loop closed from the start is
//! always seen) — port 0. If a loop is already debounced closed when it gets an ID, the lowest such
//! port is sent at once. It answers `PowerSet` / `DockConfirm` / `DockRefuse` / `DockLink` with
//! `Unsupported`.
//!
//! # Firmware update
//!
//! The node receives a signed image (`ihex-image`: header + ed25519 signature + payload) into its
//! DFU slot; the transfer messages are `ihex_proto`'s `FwBegin`, `FwData`, `FwQuery`, `FwEnd` and
//! `FwStatus` (own ID or broadcast; an unconfigured node takes no part). `Config::update` gives
//! the board, the trusted key and the flash layout. At most one transfer (a *session*) at a time:
//!
//! | phase | how it is reached | what the node does |
//! |---|---|---|
//! | `header` | `FwBegin { image_id, len, force }` | keeps frames `0..32` (the signed header) in RAM; writes nothing |
//! | — refused | the header is complete | `ihex_image::check_signed` with the node's key and policy (board, load address, protocol major, slot size, no downgrade unless `force`), the header's length against `len`, its image ID (first 4 bytes of the payload SHA-512) against `image_id`; each failure → `Refused` with its reason |
//! | `erasing` | the header passed | [`Output::EraseDfu`] for the image's length; frames are not taken |
//! | `receiving` | [`Node::handle_fw_erased`] `Ok` | the header's chunks go to flash from RAM; every further frame goes into its 24-byte chunk (4 frames, [`CHUNK_LEN`]), a complete chunk to [`Output::WriteDfu`]; up to 4 chunks are assembled at once, a fifth pushes out the one started longest ago (its frames count as missing again) |
//! | `complete` | every chunk written | waits |
//! | `verifying` | `FwEnd { Commit }` | [`Output::HashDfu`] of the header block: must equal the checked header followed by zeros; then of the payload: must equal its signed hash (else `Refused Corrupted`); then [`Output::MarkUpdated`] |
//! | `rebooting` | [`Node::handle_fw_marked`] `Ok` | [`Output::Reset`] [`RESET_DELAY_MS`] later |
//!
//! `FwStatus { phase, reason, first_missing, run, missing }` goes out when the begin arrives (or
//! is refused), when the node is ready (`receiving`, after the erase), complete, refused, verifying
//! and rebooting, and in answer to every `FwQuery`; `first_missing`/`run` name the first run of
//! missing frames (in whole chunks; header frames while in `header`), `missing` counts them all.
//! A query or end for another image than the session's is answered `idle` — or `trial` while the
//! node runs an unconfirmed image, or `reverted` when the bootloader reverted one at this boot.
//!
//! A begin with the session's image ID and length resumes it (a restarted gateway); any other
//! begin, or a begin after a refusal, starts over. While `verifying` or `rebooting`, a begin for
//! another image is answered `Refused Busy`. `FwEnd { Abort }` drops the session (not once
//! `rebooting`). A commit before `complete` only answers the status. A flash failure
//! ([`Node::handle_fw_erased`] / [`Node::handle_fw_hashed`] / [`Node::handle_fw_marked`] with
//! `Err`, [`Node::handle_fw_write_failed`]) ends the session `Refused FlashError`. The session
//! lives in RAM: after a reset the gateway starts over. No refusal touches the running image.
//!
//! **Trial boot.** With `Config::firmware.trial` (the bootloader has just swapped a new image in)
//! the node refuses every begin (`Refused Unconfirmed`: the DFU slot now holds the image to go back
//! to) and asks for [`Output::MarkBooted`] once it has *joined the bus* — any valid command from
//! the gateway arrived (the gateway checks health every second) — *and* the adapter's self-test
//! passed ([`Node::handle_self_test`]); [`Node::handle_fw_confirmed`] `Ok` clears the trial flag
//! (reported in `StateReport::Firmware`). A failed self-test asks for [`Output::Reset`] at once,
//! and an image still unconfirmed [`TRIAL_CONFIRM_MS`] after boot asks for it then: the bootloader
//! reverts it at that reset.
//!
//! # CAN controller state
//!
//! [`Node::handle_can_status`] records TEC/REC for health replies. Entering error-passive (TEC or
//! REC ≥ 128) queues `Fault { ErrorPassive, detail: TEC << 8 | REC }` once per episode (again only
//! after both fell below 128). A bus-off counts an episode; `Fault { BusOff, detail: episodes since
//! boot }` is queued when a status with `bus_off = false` follows, i.e. once it can be sent.
//!
//! # Output queue
//!
//! Outputs wait in a queue of [`OUTPUT_QUEUE_LEN`]. It only fills if the adapter stops draining;
//! then the oldest `HealthReply` or `StateReport` goes first (the gateway asks again), then the
//! oldest `BootUp`, then the oldest dock, handshake or assignment report; `Ack`s, `Fault`s and
//! non-frame outputs are never sacrificed for another output (only if nothing else is left is the
//! newest one lost). [`Node::dropped_outputs`] counts the losses. `FwStatus` reports go first, with
//! the health replies (the gateway queries again); a data frame that arrives while
//! the queue is full is not taken at all (it stays missing), so no write the core counts as done is
//! lost.
#![cfg_attr(not(test), no_std)]
#![warn(missing_docs)]
#![forbid(unsafe_code)]

mod actuator;
mod debounce;
mod node;
mod queue;
mod time;

pub use actuator::{Actuators, BuzzerOutput, LedOutput};
pub use node::{
    Config, FirmwareIdentity, FlashError, Node, Output, Retained, UpdateConfig, CHUNK_LEN,
    DEBOUNCE_MS, HANDSHAKE_SETTLE_MS, IDENTIFY_BUZZER, IDENTIFY_LED, MAX_IMAGE_LEN, RESET_DELAY_MS,
    RETAINED_WORDS, TRIAL_CONFIRM_MS, UART_IDLE_RESET_MS,
};
pub use queue::OUTPUT_QUEUE_LEN;
pub use time::Millis;
