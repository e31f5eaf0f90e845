//! The configuration record in the last flash page: load at boot, store when the node is given an ID.

use defmt::{info, warn};
use embassy_stm32::flash::{Blocking, Flash, FLASH_BASE};
use ihex_proto::BootRole;

use crate::board::{CONFIG_PAGE_ADDR, CONFIG_PAGE_SIZE};
use crate::record::{Record, RecordError, LEN};

/// Offset of the configuration page from the start of flash.
const OFFSET: u32 = CONFIG_PAGE_ADDR - FLASH_BASE as u32;

/// Why storing failed.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub enum StoreError {
    /// Erase or write reported an error.
    Flash(embassy_stm32::flash::Error),
    /// The read-back bytes differ from what was written.
    Verify,
}

/// The stored record, `None` for a factory-fresh board or an unreadable record (logged).
pub fn load(flash: &mut Flash<'_, Blocking>) -> Option<Record> {
    let mut b = [0u8; LEN];
    if let Err(e) = flash.blocking_read(OFFSET, &mut b) {
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
pub fn store(flash: &mut Flash<'_, Blocking>, record: &Record) -> Result<(), StoreError> {
    flash
        .blocking_erase(OFFSET, OFFSET + CONFIG_PAGE_SIZE)
        .map_err(StoreError::Flash)?;
    flash
        .blocking_write(OFFSET, &record.encode())
        .map_err(StoreError::Flash)?;
    let mut back = [0u8; LEN];
    flash
        .blocking_read(OFFSET, &mut back)
        .map_err(StoreError::Flash)?;
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
