//! The configuration UART (USART2 on the ST-Link virtual COM port): bytes in to the node, replies out.

use defmt::warn;
use embassy_stm32::usart::{BufferedUartRx, BufferedUartTx};
use embedded_io_async::{Read, Write};

use crate::event::{Event, EVENTS, UART_TX};

/// Forwards every received byte to the node (the core frames the 2-byte requests).
#[embassy_executor::task]
pub async fn uart_rx(mut rx: BufferedUartRx<'static>) {
    let mut buf = [0u8; 8];
    loop {
        match rx.read(&mut buf).await {
            Ok(n) => {
                for &b in &buf[..n] {
                    EVENTS.send(Event::UartByte(b)).await;
                }
            }
            // Overrun/framing/noise: the byte is lost; the core's idle timeout resynchronises.
            Err(e) => warn!("uart rx: {}", e),
        }
    }
}

/// Writes the node's replies.
#[embassy_executor::task]
pub async fn uart_tx(mut tx: BufferedUartTx<'static>) {
    loop {
        let reply = UART_TX.receive().await;
        if let Err(e) = tx.write_all(&reply).await {
            warn!("uart tx: {}", e);
        }
    }
}
