//! Images handed to the gateway over MQTT (`<island>/ihex/fw/upload/<name>`), so the lab PC
//! needs no access to the gateway's disk: each upload is checked — the [`FwImage`] checks, a
//! board this version knows and a size its slot takes, and, when the gateway is configured with
//! the lab's public key, the signature — then kept in memory under its name for `fw_update`, and
//! answered with one `fw_upload` event (`stored` or `rejected` with the reason).

use std::collections::VecDeque;

use ihex_image::{PublicKey, SIGNATURE_LEN};
use serde::{Deserialize, Serialize};

use super::image::FwImage;

/// Uploaded images kept at once; a further upload drops the oldest (one more than a lab needs
/// for an update and its way back, bounded: at most 4 × [`MAX_UPLOAD`] bytes).
pub const UPLOADS_KEPT: usize = 4;

/// The largest upload: the largest image a known board's slot takes (the F303RE's and the
/// simulator's active slot, 128 KiB, header block included). Anything larger is rejected
/// before it is parsed.
pub const MAX_UPLOAD: usize = ihex_image::board::F303RE.max_image_len() as usize;

/// Payload of `fw_upload`: the answer to one upload.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct FwUpload {
    /// The name it was uploaded under (the last topic level); `fw_update` names it so.
    pub name: String,
    /// `stored` or `rejected`.
    pub result: UploadResult,
    /// Why it was rejected.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Bytes received.
    pub len: usize,
    /// Stored: the firmware version inside.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// Stored: the board it is built for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board: Option<String>,
    /// Stored: the image's ID (8 hex digits, as `fw_report` names it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_id: Option<String>,
    /// Stored: the first 7 bytes of the payload's SHA-512 in hex, as the node state documents
    /// show the running image's hash.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_hash: Option<String>,
    /// Stored: `verified` (with the gateway's `--fw-key`) or `unchecked` (no key configured: the
    /// nodes check it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signature: Option<String>,
}

/// How an upload ended.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UploadResult {
    /// Checked and kept: `fw_update` may name it.
    Stored,
    /// Not kept (see `reason`).
    Rejected,
}

/// The uploaded images, newest last.
#[derive(Debug, Default)]
pub struct Uploads {
    images: VecDeque<(String, FwImage)>,
}

impl Uploads {
    /// The image uploaded as `name`.
    pub fn get(&self, name: &str) -> Option<&FwImage> {
        self.images.iter().find(|(n, _)| n == name).map(|(_, i)| i)
    }

    /// Checks an upload (see the module docs), keeps it when good (replacing one of the same
    /// name, dropping the oldest beyond [`UPLOADS_KEPT`]) and returns the answer to publish.
    pub fn receive(
        &mut self,
        name: &str,
        bytes: Vec<u8>,
        retained: bool,
        key: Option<&PublicKey>,
    ) -> FwUpload {
        let len = bytes.len();
        let mut answer = FwUpload {
            name: name.to_owned(),
            result: UploadResult::Rejected,
            reason: None,
            len,
            version: None,
            board: None,
            image_id: None,
            image_hash: None,
            signature: None,
        };
        match check(name, bytes, retained, key) {
            Err(why) => answer.reason = Some(why),
            Ok(image) => {
                let h = image.header();
                answer.result = UploadResult::Stored;
                answer.version = Some(h.version.to_string());
                answer.board = Some(h.board.to_string());
                answer.image_id = Some(format!("{:08x}", image.image_id()));
                answer.image_hash =
                    Some(ihex_proto::Hex(&h.payload_hash.prefix::<7>()).to_string());
                answer.signature = Some(
                    if key.is_some() {
                        "verified"
                    } else {
                        "unchecked"
                    }
                    .into(),
                );
                self.images.retain(|(n, _)| n != name);
                if self.images.len() >= UPLOADS_KEPT {
                    self.images.pop_front();
                }
                self.images.push_back((name.to_owned(), image));
            }
        }
        answer
    }
}

fn check(
    name: &str,
    bytes: Vec<u8>,
    retained: bool,
    key: Option<&PublicKey>,
) -> Result<FwImage, String> {
    if !crate::command::is_image_name(name) {
        return Err(format!(
            "{name:?} is not an image name (1 to 128 of A-Z a-z 0-9 . - _, not starting with '.')"
        ));
    }
    if retained {
        // A retained upload would be stored again at every reconnection, and sit in the broker.
        return Err("retained uploads are not taken: publish with the retain flag off".into());
    }
    if bytes.len() > MAX_UPLOAD {
        return Err(format!(
            "{} bytes is larger than an image slot takes ({MAX_UPLOAD} bytes)",
            bytes.len()
        ));
    }
    let image = FwImage::check(bytes).map_err(|e| e.to_string())?;
    let header = *image.header();
    let layout = header
        .board
        .layout()
        .ok_or_else(|| format!("board {} is not one this gateway knows", header.board))?;
    if image.len() > layout.max_image_len() {
        return Err(format!(
            "image of {} bytes does not fit the {} slot ({} bytes)",
            image.len(),
            header.board,
            layout.max_image_len()
        ));
    }
    if let Some(key) = key {
        if header.key_id != key.id() {
            return Err(format!(
                "signed with key {}, not with the gateway's key {}",
                header.key_id,
                key.id()
            ));
        }
        let bytes = image.bytes();
        let mut signature = [0u8; SIGNATURE_LEN];
        signature.copy_from_slice(&bytes[ihex_image::header::field::SIGNATURE]);
        key.verify(&bytes[..ihex_image::HEADER_LEN], &signature)
            .map_err(|e| format!("the signature does not verify: {e}"))?;
    }
    Ok(image)
}

#[cfg(test)]
mod tests {
    use ihex_image::{pack, Board, FirmwareVersion, SigningKey};

    use super::*;

    fn image(board: Board, payload: usize, key: &SigningKey) -> Vec<u8> {
        pack(
            board,
            (1, 2),
            FirmwareVersion::new(2, 0, 0),
            &vec![0x5a; payload],
            key,
        )
        .unwrap()
    }

    fn rejected(u: &mut Uploads, name: &str, bytes: Vec<u8>, key: Option<&PublicKey>) -> String {
        let a = u.receive(name, bytes, false, key);
        assert_eq!(a.result, UploadResult::Rejected, "{a:?}");
        assert!(u.get(name).is_none());
        a.reason.unwrap()
    }

    #[test]
    fn a_good_upload_is_stored_and_answered_with_its_identity() {
        let key = SigningKey::test_key();
        let bytes = image(Board::SIM, 1000, &key);
        let mut u = Uploads::default();
        let a = u.receive("new.ihex", bytes.clone(), false, Some(&key.public()));
        assert_eq!(a.result, UploadResult::Stored, "{a:?}");
        assert_eq!(a.version.as_deref(), Some("2.0.0"));
        assert_eq!(a.board.as_deref(), Some("sim"));
        assert_eq!(a.signature.as_deref(), Some("verified"));
        assert_eq!(a.len, bytes.len());
        let stored = u.get("new.ihex").unwrap();
        assert_eq!(a.image_id, Some(format!("{:08x}", stored.image_id())));
        assert_eq!(a.image_hash.as_ref().map(String::len), Some(14));
        // Without a key the gateway checks everything but the signature, and says so.
        let a = u.receive("other", bytes, false, None);
        assert_eq!(a.signature.as_deref(), Some("unchecked"));
    }

    #[test]
    fn bad_uploads_are_rejected_with_a_reason() {
        let key = SigningKey::test_key();
        let lab = key.public();
        let good = image(Board::SIM, 1000, &key);
        let mut u = Uploads::default();

        let stranger = SigningKey::generate().unwrap();
        let why = rejected(&mut u, "a", image(Board::SIM, 1000, &stranger), Some(&lab));
        assert!(why.contains("not with the gateway's key"), "{why}");

        // A header changed after signing (the version), with its ID kept.
        let mut forged = good.clone();
        forged[ihex_image::header::field::VERSION.start] ^= 1;
        let why = rejected(&mut u, "a", forged, Some(&lab));
        assert!(why.contains("signature"), "{why}");

        let why = rejected(&mut u, "a", good[..good.len() - 1].to_vec(), Some(&lab));
        assert!(why.contains("truncated") || why.contains("short"), "{why}");

        let mut corrupted = good.clone();
        *corrupted.last_mut().unwrap() ^= 0xff;
        let why = rejected(&mut u, "a", corrupted, Some(&lab));
        assert!(why.contains("hash"), "{why}");

        // (The board is checked before the signature, so the patched header needs no new one.)
        let mut alien = good.clone();
        alien[ihex_image::header::field::BOARD].copy_from_slice(&0x0777u16.to_le_bytes());
        let why = rejected(&mut u, "a", alien, Some(&lab));
        assert!(why.contains("board 0x0777"), "{why}");

        let why = rejected(&mut u, "a", vec![0; MAX_UPLOAD + 1], Some(&lab));
        assert!(why.contains("larger than an image slot"), "{why}");

        let why = rejected(&mut u, "a", b"not an image".to_vec(), Some(&lab));
        assert!(why.starts_with("bad image"), "{why}");

        let why = rejected(&mut u, "../x", good.clone(), Some(&lab));
        assert!(why.contains("not an image name"), "{why}");

        let a = u.receive("a", good, true, Some(&lab));
        assert_eq!(a.result, UploadResult::Rejected);
        assert!(a.reason.unwrap().contains("retain"));
    }

    #[test]
    fn at_most_a_few_uploads_are_kept_the_oldest_go_first() {
        let key = SigningKey::test_key();
        let bytes = image(Board::SIM, 100, &key);
        let mut u = Uploads::default();
        for n in 0..=UPLOADS_KEPT {
            u.receive(&format!("i{n}"), bytes.clone(), false, None);
        }
        assert!(u.get("i0").is_none());
        assert!((1..=UPLOADS_KEPT).all(|n| u.get(&format!("i{n}")).is_some()));
        // The same name again replaces, and counts as the newest.
        u.receive("i1", bytes.clone(), false, None);
        u.receive("j", bytes, false, None);
        assert!(u.get("i1").is_some() && u.get("i2").is_none());
    }
}
