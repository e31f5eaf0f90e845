//! The configuration record in the last flash page (its own partition of the flash layout): load at
//! boot, store when the node is given an ID.

use defmt::{info, warn};
use embedded_storage::nor_flash::{NorFlash, ReadNorFlash};
use ihex_proto::BootRole;

use crate::record::{Record, RecordError, LEN};
use crate::update::Part;

/// Why storing failed.
#[derive(Debug, defmt::Format)]
pub enum StoreError {
    /// Erase or write reported an error.
    Flash(embassy_embedded_hal::flash::partition::Error<embassy_stm32::flash::Error>),
    /// The read-back bytes differ from what was written.
    Verify,
}

/// The stored record, `None` for a factory-fresh board or an unreadable record (logged).
pub fn load(page: &mut Part) -> Option<Record> {
    let mut b = [0u8; LEN];
    if let Err(e) = page.read(0, &mut b) {
        warn!("config: read failed: {}", e);
        return None;
    }
    match Record::decode(&b) {
        Ok(r) => Some(r),
        Err(RecordError::Erased) => {
            info!("config: no node ID stored (factory-fresh), waiting for one");
            None
        }
        Err(e) => {
            warn!(
                "config: stored record rejected ({}), treating as unconfigured",
                e
            );
            None
        }
    }
}

/// Erases the page and writes `record`, then reads it back.
pub fn store(page: &mut Part, record: &Record) -> Result<(), StoreError> {
    let len = page.capacity() as u32;
    page.erase(0, len).map_err(StoreError::Flash)?;
    page.write(0, &record.encode()).map_err(StoreError::Flash)?;
    let mut back = [0u8; LEN];
    page.read(0, &mut back).map_err(StoreError::Flash)?;
    if Record::decode(&back) != Ok(*record) {
        return Err(StoreError::Verify);
    }
    Ok(())
}

/// Logs when the role jumper no longer matches the role the ID was stored under.
pub fn check_role(record: &Record, jumper: BootRole) {
    if record.role != jumper {
        warn!(
            "config: ID {} was stored as {} but the role jumper now says {}",
            record.node_id, record.role, jumper
        );
    }
}
