//! The firmware's tasks, one per role; each owns its peripheral driver. The relay is driven by the
//! node task itself (see [`relay`]), so that it switches before the frame that goes with it leaves.
//!
//! | task            | owns                         | in                         | out                      |
//! |-----------------|------------------------------|----------------------------|--------------------------|
//! | `node`          | `ihex_sc_core::Node`, flash, relay GPIO | `EVENTS`, timer | relay, `CAN_TX`, `UART_TX`, `FILTERS`, `LED`, `BUZZER` |
//! | `can_rx`        | `CanRx` (+ filter banks)     | bus, `FILTERS`             | `EVENTS::Frame`, `FILTERS_DONE` |
//! | `can_tx`        | `CanTx`                      | `CAN_TX`                   | bus                      |
//! | `can_status`    | (reads `CAN_ESR`)            | 100 ms poll                | `EVENTS::CanStatus`      |
//! | `led`           | TIM1 CH1–3, TIM3 CH1         | `LED`                      | PWM                      |
//! | `buzzer`        | TIM15 CH2                    | `BUZZER`                   | PWM, `EVENTS::BuzzerDone`|
//! //! | `signal_loop`×6 | one `ExtiInput` each         | edges + 100 ms poll        | `EVENTS::Loop`           |
//! | `uart_rx/tx`    | `BufferedUart` halves        | USART2, `UART_TX`          | `EVENTS::UartByte`, USART2 |
//! | `watchdog`      | IWDG, status LED             | heartbeats                 | IWDG refresh             |

pub mod buzzer;
pub mod can;
pub mod led;
pub mod node;
pub mod relay;
pub mod signal_loop;
pub mod uart;
pub mod watchdog;
