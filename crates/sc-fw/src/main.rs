//! iHEX sub-controller firmware: chip set-up, then the tasks of `ihex_sc_fw::tasks` run the node.
#![no_std]
#![no_main]

use defmt::{info, unwrap, warn};
use embassy_executor::Spawner;
use embassy_stm32::can::Can;
use embassy_stm32::exti::ExtiInput;
use embassy_stm32::flash::Flash;
use embassy_stm32::gpio::{Input, Level, Output, OutputType, Speed};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::CountingMode;
use embassy_stm32::timer::simple_pwm::{PwmPin, SimplePwm};
use embassy_stm32::usart::{self, BufferedUart};
use embassy_stm32::{bind_interrupts, can, peripherals};
use ihex_proto::{BootRole, Port, Uid};
use ihex_sc_core::Node;
use ihex_sc_fw::board::{self, ExtiIrqs};
use ihex_sc_fw::tasks::{self, led::PWM_HZ, node::now};
use ihex_sc_fw::{can as sc_can, clock, config, image, reset, retained, take_board, update};
use static_cell::StaticCell;
use {defmt_rtt as _, panic_probe as _};

bind_interrupts!(struct Irqs {
    USB_LP_CAN_RX0 => can::Rx0InterruptHandler<peripherals::CAN>;
    CAN_RX1 => can::Rx1InterruptHandler<peripherals::CAN>;
    CAN_SCE => can::SceInterruptHandler<peripherals::CAN>;
    USB_HP_CAN_TX => can::TxInterruptHandler<peripherals::CAN>;
    USART2 => usart::BufferedInterruptHandler<peripherals::USART2>;
});

/// Dock ports of a hexagonal element (signal loops `loop0`..`loop5` of the pin map).
const PORTS: u8 = 6;

static CAN: StaticCell<Can<'static>> = StaticCell::new();
static NODE: StaticCell<Node> = StaticCell::new();
static UART_TX_BUF: StaticCell<[u8; 32]> = StaticCell::new();
static UART_RX_BUF: StaticCell<[u8; 64]> = StaticCell::new();

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let p = embassy_stm32::init(clock::config());
    let reset = reset::take_reset_reason();
    let kept = retained::take(reset);
    let b = take_board!(p);

    // First of all: the relay is driven off (it was already off through reset by its pull-down),
    // unless this start follows a reset the node asked for with the relay on: then the bootloader
    // drove it on again and it stays on without a gap.
    let relay_on = kept.is_some_and(|k| k.relay);
    let relay = Output::new(
        b.relay,
        if relay_on != board::RELAY_ACTIVE_LOW {
            Level::High
        } else {
            Level::Low
        },
        Speed::Low,
    );

    let role_pin = Input::new(b.role, board::ROLE_PULL);
    cortex_m::asm::delay(720); // 10 µs for the pull-up to charge the jumper pin
    let role = if role_pin.is_low() == board::ROLE_ACTIVE_LOW {
        BootRole::Mobile
    } else {
        BootRole::Static
    };
    drop(role_pin);

    let mut parts = update::split(Flash::new_blocking(p.FLASH));
    let mut updater = update::Updater::new(parts.dfu, parts.state);
    let boot_state = updater.boot_state();
    let header = update::running_header(&mut parts.active);
    match (&header, image::stored_info()) {
        (Some(h), _) => info!(
            "image: {} {}, protocol {}.{}, sha512 {}, {}",
            h.board, h.version, h.protocol.0, h.protocol.1, h.payload_hash, boot_state
        ),
        (None, info) => info!(
            "image: no header in the active slot (flashed by probe-rs), built as {}, {}",
            info, boot_state
        ),
    }
    let record = config::load(&mut parts.config);
    if let Some(r) = &record {
        config::check_role(r, role);
    }
    let node_id = record.map(|r| r.node_id);
    let uid = Uid(embassy_stm32::uid::uid());
    info!(
        "iHEX SC {} up: reset {}, role {}, node ID {}, uid {=[u8]:02x}",
        image::VERSION,
        reset,
        role,
        node_id,
        uid.0
    );

    // CAN: the protocol's bit timing and filter banks, both read back from the registers.
    let timing = unwrap!(sc_can::bit_timing());
    let can = CAN.init(Can::new(p.CAN, b.can_rx, b.can_tx, Irqs));
    can.modify_config()
        .set_bit_timing(unwrap!(sc_can::nominal(&timing)))
        .set_loopback(false)
        .set_silent(false)
        .set_automatic_retransmit(true);
    // Mailboxes leave in the order the core queued the frames (its order is part of its contract),
    // not re-sorted by identifier.
    can.set_tx_fifo_scheduling(true);
    let banks = unwrap!(sc_can::banks_for(node_id));
    unwrap!(sc_can::apply_filters(&mut can.modify_filters(), &banks));
    can.enable().await;
    // The self-test a new image on trial must pass before it confirms itself.
    let self_test = sc_can::verify_bit_timing(&timing) && sc_can::verify_filters(&banks);
    if !self_test {
        warn!("CAN registers differ from the protocol's values (see above)");
    }
    let (can_tx, can_rx) = can.split();

    let rgb = SimplePwm::new(
        p.TIM1,
        Some(PwmPin::new(b.led_r, OutputType::PushPull)),
        Some(PwmPin::new(b.led_g, OutputType::PushPull)),
        Some(PwmPin::new(b.led_b, OutputType::PushPull)),
        None,
        Hertz(PWM_HZ),
        CountingMode::EdgeAlignedUp,
    );
    let gate = SimplePwm::new(
        p.TIM3,
        Some(PwmPin::new(b.led_blink, OutputType::PushPull)),
        None,
        None,
        None,
        Hertz(1),
        CountingMode::EdgeAlignedUp,
    );
    let buzzer = SimplePwm::new(
        p.TIM15,
        None,
        Some(PwmPin::new(b.buzzer, OutputType::PushPull)),
        None,
        None,
        Hertz(2_000),
        CountingMode::EdgeAlignedUp,
    );

    let mut uart_cfg = usart::Config::default();
    uart_cfg.baudrate = ihex_proto::uart::BAUD;
    uart_cfg.rx_pull = board::UART_RX_PULL;
    let uart = unwrap!(BufferedUart::new(
        p.USART2,
        b.uart_rx,
        b.uart_tx,
        UART_TX_BUF.init([0; 32]),
        UART_RX_BUF.init([0; 64]),
        Irqs,
        uart_cfg,
    ));
    let (uart_tx, uart_rx) = uart.split();

    let loops = [
        ExtiInput::new(b.loop0, b.loop0_exti, board::LOOP0_PULL, ExtiIrqs),
        ExtiInput::new(b.loop1, b.loop1_exti, board::LOOP1_PULL, ExtiIrqs),
        ExtiInput::new(b.loop2, b.loop2_exti, board::LOOP2_PULL, ExtiIrqs),
        ExtiInput::new(b.loop3, b.loop3_exti, board::LOOP3_PULL, ExtiIrqs),
        ExtiInput::new(b.loop4, b.loop4_exti, board::LOOP4_PULL, ExtiIrqs),
        ExtiInput::new(b.loop5, b.loop5_exti, board::LOOP5_PULL, ExtiIrqs),
    ];
    let loop_active_low = [
        board::LOOP0_ACTIVE_LOW,
        board::LOOP1_ACTIVE_LOW,
        board::LOOP2_ACTIVE_LOW,
        board::LOOP3_ACTIVE_LOW,
        board::LOOP4_ACTIVE_LOW,
        board::LOOP5_ACTIVE_LOW,
    ];

    // In a static, not in the node task's future: the node (its update receiver above all) is a
    // few KiB, which the future would otherwise hold twice (argument and local).
    let node = NODE.init(Node::new(
        ihex_sc_core::Config {
            role,
            ports: PORTS,
            uid,
            node_id,
            reset,
            firmware: image::identity(header.as_ref(), boot_state),
            update: image::update_config(boot_state),
        },
        now(),
    ));
    if let Some(kept) = kept {
        // The closed loops first, as `Node::restore` wants (the loop tasks report them again,
        // which changes nothing), so a still-docked port is kept at the restore's check.
        for (i, (pin, &active_low)) in loops.iter().zip(&loop_active_low).enumerate() {
            if pin.is_low() == active_low {
                node.handle_loop_level(unwrap!(Port::new(i as u8)), true, now());
            }
        }
        info!("relay kept across the software reset: {}", kept);
        node.restore(kept, now());
    }

    let status_led = Output::new(b.status_led, Level::Low, Speed::Low);
    spawner.spawn(unwrap!(tasks::watchdog::watchdog(p.IWDG, status_led)));
    spawner.spawn(unwrap!(tasks::led::led(rgb, gate)));
    spawner.spawn(unwrap!(tasks::buzzer::buzzer(buzzer)));
    spawner.spawn(unwrap!(tasks::can::can_rx(can_rx)));
    spawner.spawn(unwrap!(tasks::can::can_tx(can_tx)));
    spawner.spawn(unwrap!(tasks::can::can_status()));
    spawner.spawn(unwrap!(tasks::uart::uart_rx(uart_rx)));
    spawner.spawn(unwrap!(tasks::uart::uart_tx(uart_tx)));
    for (i, (pin, active_low)) in loops.into_iter().zip(loop_active_low).enumerate() {
        let port = unwrap!(Port::new(i as u8));
        spawner.spawn(unwrap!(tasks::signal_loop::signal_loop(
            port, pin, active_low
        )));
    }
    let relay = tasks::relay::Relay::new(relay, board::RELAY_ACTIVE_LOW);
    spawner.spawn(unwrap!(tasks::node::node(
        node,
        parts.config,
        updater,
        relay,
        role,
        self_test
    )));
}
