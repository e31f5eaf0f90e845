//! Records the build year (`IHEX_BUILD_YEAR`) for `mc-gateway doctor`'s clock check: a clock before
//! the year the binary was built is certainly wrong. `SOURCE_DATE_EPOCH` fixes it for reproducible
//! builds.

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
}
