//! Records the build year (`IHEX_BUILD_YEAR`) for `mc-gateway doctor`'s clock check: a clock before
//! the year the binary was built is certainly wrong. `SOURCE_DATE_EPOCH` fixes it for reproducible
//! builds. With the `sila` feature, also generates the SiLA 2 gRPC code from the vendored protos in
//! `sila/proto` (compiled by protox, so no system `protoc` is needed).

#[path = "src/doctor/calendar.rs"]
mod calendar;

fn main() {
    println!("cargo:rerun-if-env-changed=SOURCE_DATE_EPOCH");
    println!("cargo:rerun-if-changed=src/doctor/calendar.rs");
    let secs = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|s| s.trim().parse::<u64>().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs())
        });
    println!(
        "cargo:rustc-env=IHEX_BUILD_YEAR={}",
        calendar::year_of(secs)
    );
    #[cfg(feature = "sila")]
    sila();
}

/// The SiLA protos, compiled in order (each after what it imports).
#[cfg(feature = "sila")]
fn sila() {
    const PROTOS: [&str; 6] = [
        "sila/proto/SiLAFramework.proto",
        "sila/proto/SiLAService.proto",
        "sila/proto/LockController.proto",
        "sila/proto/IslandControl.proto",
        "sila/proto/FirmwareUpdate.proto",
        "sila/proto/CancelController.proto",
    ];
    for p in PROTOS {
        println!("cargo:rerun-if-changed={p}");
    }
    let fds = protox::compile(PROTOS, ["sila/proto"]).expect("compiling the SiLA protos");
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        // prost's codec with buffers sized for SiLA's messages (`src/sila/codec.rs`).
        .codec_path("crate::sila::codec::SilaCodec")
        .compile_fds(fds)
        .expect("generating the SiLA gRPC code");
}
