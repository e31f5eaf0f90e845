//! The channels and signals between the tasks: one event channel into the node task, latest-value
//! signals out of it to the LED and buzzer tasks, bounded queues to the CAN and UART transmitters.

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::channel::Channel;
use embassy_sync::signal::Signal;
use ihex_proto::{NodeId, Packet, Port};
use ihex_sc_core::{BuzzerOutput, LedOutput};

/// A received CAN frame, as the core takes it.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub struct RxFrame {
    /// Raw identifier (11 or 29 bits).
    pub raw_id: u32,
    /// Extended (29-bit) identifier.
    pub extended: bool,
    /// Remote frame.
    pub remote: bool,
    /// Data length (0–8).
    pub len: u8,
    /// Data bytes (`len` valid).
    pub data: [u8; 8],
}

/// The bxCAN controller's error state.
#[derive(Clone, Copy, PartialEq, Eq, Debug, defmt::Format)]
pub struct CanStatus {
    /// Transmit error counter.
    pub tec: u8,
    /// Receive error counter.
    pub rec: u8,
    /// Bus-off (the hardware recovers by itself: ABOM is set).
    pub bus_off: bool,
}

/// An input for the node task.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub enum Event {
    /// A frame passed the acceptance filters.
    Frame(RxFrame),
    /// A signal loop's raw level (`closed` = pulled low = docked); the core debounces.
    Loop {
        /// Dock port.
        port: Port,
        /// Loop closed.
        closed: bool,
    },
    /// One byte from the configuration UART.
    UartByte(u8),
    /// The CAN error counters changed.
    CanStatus(CanStatus),
    /// The buzzer task finished a finite pattern.
    BuzzerDone,
}

type Mutex = CriticalSectionRawMutex;

/// Everything the node task reacts to.
pub static EVENTS: Channel<Mutex, Event, 32> = Channel::new();
/// Frames to transmit. As deep as the core's output queue, so that everything one pass of the node
/// task drains (a full state reply is 16 frames) fits while the transmitter catches up.
pub static CAN_TX: Channel<Mutex, Packet, { ihex_sc_core::OUTPUT_QUEUE_LEN }> = Channel::new();
/// Replies for the configuration UART.
pub static UART_TX: Channel<Mutex, [u8; 2], 4> = Channel::new();
/// New acceptance filters are needed for this node ID (`None` = unconfigured: broadcasts only).
pub static FILTERS: Signal<Mutex, Option<NodeId>> = Signal::new();
/// LED strip setting.
pub static LED: Signal<Mutex, LedOutput> = Signal::new();
/// Buzzer setting.
pub static BUZZER: Signal<Mutex, BuzzerOutput> = Signal::new();
/// The CAN receive task installed the filters asked for through [`FILTERS`].
pub static FILTERS_DONE: Signal<Mutex, ()> = Signal::new();
