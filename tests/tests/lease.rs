//! `can::lease` hands out each listed interface once, then fails loudly.
//!
//! One test in its own binary: it sets `IHEX_TEST_CAN` for the whole process.

#[test]
fn lease_hands_out_each_interface_once() {
    std::env::set_var(ihex_tests::can::ENV, " vcanA, vcanB ,");
    assert_eq!(ihex_tests::can::lease(), "vcanA");
    assert_eq!(ihex_tests::can::lease(), "vcanB");
    let err = std::panic::catch_unwind(ihex_tests::can::lease).expect_err("third lease");
    let msg = err
        .downcast_ref::<String>()
        .expect("formatted panic message");
    assert!(msg.contains("all 2 interfaces"), "{msg}");

    std::env::remove_var(ihex_tests::can::ENV);
    let err = std::panic::catch_unwind(ihex_tests::can::lease).expect_err("no variable");
    let msg = err
        .downcast_ref::<String>()
        .expect("formatted panic message");
    assert!(msg.contains("cargo xtask test"), "{msg}");
}
