//! The firmware's tasks, one per role; each owns its peripheral driver.
//!
//! | task            | owns                         | in                         | out                      |
//! |-----------------|------------------------------|----------------------------|--------------------------|
//! | `node`          | `ihex_sc_core::Node`, flash  | `EVENTS`, timer            | `CAN_TX`, `UART_TX`, `FILTERS`, `LED`, `BUZZER`, `RELAY` |
//! | `can_rx`        | `CanRx` (+ filter banks)     | bus, `FILTERS`             | `EVENTS::Frame`          |
//! | `can_tx`        | `CanTx`                      | `CAN_TX`                   | bus                      |
//! | `can_status`    | (reads `CAN_ESR`)            | 100 ms poll                | `EVENTS::CanStatus`      |
//! | `led`           | TIM1 CH1–3, TIM3 CH1         | `LED`                      | PWM                      |
//! | `buzzer`        | TIM15 CH2                    | `BUZZER`                   | PWM, `EVENTS::BuzzerDone`|
//! | `relay`         | relay GPIO                   | `RELAY`                    | GPIO                     |
//! | `signal_loop`×6 | one `ExtiInput` each         | edges + 100 ms poll        | `EVENTS::Loop`           |
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
