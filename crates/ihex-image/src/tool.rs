//! Host tools (`std`): signing keys, packing a payload into a signed image, inspecting an image.

use std::fmt;
use std::fs;
use std::io::Write;
use std::path::Path;

use crate::board::Board;
use crate::check::{check_len, Hasher};
use crate::error::{ImageError, KeyTextError};
use crate::header::{field, Header, HEADER_BLOCK, HEADER_LEN, SIGNED_LEN};
use crate::hex::parse_key_text;
use crate::key::{PublicKey, SIGNATURE_LEN};
use crate::FirmwareVersion;

/// What the tools can fail at.
#[derive(Debug, thiserror::Error)]
pub enum ToolError {
    /// Reading or writing a file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// What happened.
        source: std::io::Error,
    },
    /// A key file that does not parse.
    #[error("{path}: {source}")]
    KeyText {
        /// The file.
        path: String,
        /// Why.
        source: KeyTextError,
    },
    /// The operating system's random source failed.
    #[error("no randomness for a new key: {0}")]
    Random(String),
    /// A file that should be written already exists.
    #[error("{0} exists; refusing to overwrite a key")]
    Exists(String),
    /// No layout is known for the board.
    #[error("no flash layout is known for board {0}")]
    UnknownBoard(Board),
    /// The payload is empty or does not fit the board's slot.
    #[error("payload of {len} bytes: a slot of board {board} takes 1..={max}")]
    PayloadSize {
        /// The board.
        board: Board,
        /// Payload bytes.
        len: usize,
        /// The largest payload.
        max: u32,
    },
    /// Release notes that do not fit the header block's notes area.
    #[error("release notes of {0} bytes: at most {max} bytes of text without NUL", max = crate::NOTES_LEN)]
    NotesSize(usize),
    /// The firmware ELF cannot be flattened.
    #[error("ELF: {0}")]
    Elf(#[from] crate::elf::ElfError),
    /// The ELF has no identity record and no value was given for this header field.
    #[error("the ELF has no IHEX_FW_INFO record: give the {0}")]
    InfoMissing(&'static str),
    /// A given header field contradicts the ELF's identity record.
    #[error("the ELF was built as {field} {elf}, not {given} (change the firmware's crate version instead)")]
    InfoMismatch {
        /// The field.
        field: &'static str,
        /// What the ELF says.
        elf: String,
        /// What was given.
        given: String,
    },
    /// An image that cannot be read at all.
    #[error("not an image: {0}")]
    Image(ImageError),
}

/// An ed25519 signing key (its 32-byte seed). Kept by the lab, never on the bench.
#[derive(Clone)]
pub struct SigningKey {
    seed: [u8; 32],
}

impl fmt::Debug for SigningKey {
    /// Shows the public half only.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "SigningKey(public {})", self.public())
    }
}

impl SigningKey {
    /// A new key from the operating system's random source.
    pub fn generate() -> Result<Self, ToolError> {
        let mut seed = [0u8; 32];
        getrandom::fill(&mut seed).map_err(|e| ToolError::Random(e.to_string()))?;
        Ok(SigningKey { seed })
    }

    /// The key with this seed.
    pub const fn from_seed(seed: [u8; 32]) -> Self {
        SigningKey { seed }
    }

    /// The committed test key (tests and simulator only, see [`crate::test_key`]).
    pub const fn test_key() -> Self {
        SigningKey::from_seed(crate::test_key::SEED)
    }

    /// Parses a secret key file's text.
    pub fn from_text(text: &str) -> Result<Self, KeyTextError> {
        Ok(SigningKey {
            seed: parse_key_text(text)?,
        })
    }

    /// Reads a secret key file.
    pub fn load(path: &Path) -> Result<Self, ToolError> {
        let text = read_text(path)?;
        SigningKey::from_text(&text).map_err(|source| ToolError::KeyText {
            path: path.display().to_string(),
            source,
        })
    }

    /// The public half.
    pub fn public(&self) -> PublicKey {
        PublicKey::from_bytes(salty::Keypair::from(&self.seed).public.to_bytes())
    }

    /// The ed25519 signature of `message`.
    pub fn sign(&self, message: &[u8]) -> [u8; SIGNATURE_LEN] {
        salty::Keypair::from(&self.seed).sign(message).to_bytes()
    }

    /// The secret key file's text.
    pub fn secret_text(&self) -> String {
        let mut s = format!(
            "# iHEX firmware signing key (ed25519 seed) for public key ID {}.\n\
             # SECRET: whoever has this file can sign firmware your boards accept.\n",
            self.public().id()
        );
        for b in self.seed {
            s.push_str(&format!("{b:02x}"));
        }
        s.push('\n');
        s
    }

    /// The public key file's text.
    pub fn public_text(&self) -> String {
        let public = self.public();
        format!(
            "# iHEX firmware public key, ID {}. Build the firmware with IHEX_FW_PUBKEY=<this file>.\n{public}\n",
            public.id()
        )
    }

    /// Writes `<stem>.secret` (mode 0600) and `<stem>.pub` next to each other; refuses to
    /// overwrite either.
    pub fn save(&self, secret: &Path, public: &Path) -> Result<(), ToolError> {
        for p in [secret, public] {
            if p.exists() {
                return Err(ToolError::Exists(p.display().to_string()));
            }
        }
        let io = |path: &Path| {
            let path = path.display().to_string();
            move |source| ToolError::Io { path, source }
        };
        let mut opts = fs::OpenOptions::new();
        opts.write(true).create_new(true);
        #[cfg(unix)]
        std::os::unix::fs::OpenOptionsExt::mode(&mut opts, 0o600);
        opts.open(secret)
            .and_then(|mut f| f.write_all(self.secret_text().as_bytes()))
            .map_err(io(secret))?;
        fs::write(public, self.public_text()).map_err(io(public))?;
        Ok(())
    }
}

/// Reads a public key file.
pub fn load_public(path: &Path) -> Result<PublicKey, ToolError> {
    let text = read_text(path)?;
    PublicKey::from_text(&text).map_err(|source| ToolError::KeyText {
        path: path.display().to_string(),
        source,
    })
}

fn read_text(path: &Path) -> Result<String, ToolError> {
    fs::read_to_string(path).map_err(|source| ToolError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Signs `payload` into an image file for `board` (header block + payload): the header carries
/// the board, `protocol`, `version`, the payload's length and SHA-512, the board's load address
/// and the key's ID.
pub fn pack(
    board: Board,
    protocol: (u8, u8),
    version: FirmwareVersion,
    payload: &[u8],
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    pack_with_notes(board, protocol, version, payload, "", key)
}

/// [`pack`] with release notes: a non-empty `notes` makes a format-2 image carrying them
/// ([`crate::header`]); empty notes, a format-1 image.
pub fn pack_with_notes(
    board: Board,
    protocol: (u8, u8),
    version: FirmwareVersion,
    payload: &[u8],
    notes: &str,
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    let area = crate::notes_area(notes).ok_or(ToolError::NotesSize(notes.len()))?;
    let layout = board.layout().ok_or(ToolError::UnknownBoard(board))?;
    let max = layout.max_payload_len();
    if payload.is_empty() || payload.len() > max as usize {
        return Err(ToolError::PayloadSize {
            board,
            len: payload.len(),
            max,
        });
    }
    let header = Header {
        board,
        protocol,
        version,
        payload_len: payload.len() as u32,
        load_addr: layout.app_start(),
        key_id: key.public().id(),
        payload_hash: Hasher::digest(payload),
        notes_hash: (!notes.is_empty()).then(|| crate::notes_hash(&area)),
    };
    let bytes = header.encode();
    let mut image = Vec::with_capacity(HEADER_BLOCK + payload.len());
    image.extend_from_slice(&bytes);
    image.extend_from_slice(&key.sign(&bytes));
    image.extend_from_slice(&area);
    image.extend_from_slice(payload);
    Ok(image)
}

/// Header fields for [`pack_elf`] where the ELF has no [`crate::FwInfo`] record; where it has one,
/// they must agree with it (an image never claims another version than its code was built as).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PackOverrides {
    /// The board.
    pub board: Option<Board>,
    /// The protocol version (major, minor).
    pub protocol: Option<(u8, u8)>,
    /// The firmware version.
    pub version: Option<FirmwareVersion>,
}

/// Packs a firmware ELF: its [`crate::FwInfo`] record (or `overrides`) gives board, protocol and
/// version; its loadable segments, flattened at the board's load address, are the payload.
pub fn pack_elf(
    elf: &[u8],
    overrides: PackOverrides,
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    pack_elf_with_notes(elf, overrides, "", key)
}

/// [`pack_elf`] with release notes (see [`pack_with_notes`]).
pub fn pack_elf_with_notes(
    elf: &[u8],
    overrides: PackOverrides,
    notes: &str,
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    let info = crate::elf::fw_info(elf)?;
    fn pick<T: Copy + PartialEq + fmt::Display>(
        field: &'static str,
        from_elf: Option<T>,
        given: Option<T>,
    ) -> Result<T, ToolError> {
        match (from_elf, given) {
            (Some(e), Some(g)) if e != g => Err(ToolError::InfoMismatch {
                field,
                elf: e.to_string(),
                given: g.to_string(),
            }),
            (Some(v), _) | (None, Some(v)) => Ok(v),
            (None, None) => Err(ToolError::InfoMissing(field)),
        }
    }
    let board = pick("board", info.map(|i| i.board), overrides.board)?;
    let version = pick("version", info.map(|i| i.version), overrides.version)?;
    let protocol = pick(
        "protocol",
        info.map(|i| ProtocolVersion(i.protocol)),
        overrides.protocol.map(ProtocolVersion),
    )?
    .0;
    let layout = board.layout().ok_or(ToolError::UnknownBoard(board))?;
    let flat = crate::elf::flatten(elf, layout.app_start(), layout.max_payload_len())?;
    pack_with_notes(board, protocol, version, &flat.bytes, notes, key)
}

/// `major.minor`, for messages.
#[derive(Clone, Copy, PartialEq, Eq)]
struct ProtocolVersion((u8, u8));

impl fmt::Display for ProtocolVersion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{}", self.0 .0, self.0 .1)
    }
}

/// What an image says about itself, and which of its checks pass. Unlike
/// [`crate::verify_image`] it does not stop at the first problem and needs no node policy.
#[derive(Clone, Debug)]
pub struct Inspection {
    /// The header (format checks passed).
    pub header: Header,
    /// The file's length against the header's.
    pub length: Result<(), ImageError>,
    /// The notes area after the signature is zero (format 1) or hashes to `notes_hash` (format 2).
    pub padding_ok: bool,
    /// The release notes (format 2, when they check out and are UTF-8).
    pub notes: Option<String>,
    /// The payload hashes to `payload_hash` (false when the file is too short to tell).
    pub payload_ok: bool,
    /// The signature checked with the given key; `None` when no key was given.
    pub signature: Option<Result<(), ImageError>>,
}

impl Inspection {
    /// Inspects `image`; `key` checks the signature. Fails only when there is no readable header.
    pub fn of(image: &[u8], key: Option<&PublicKey>) -> Result<Inspection, ToolError> {
        let header = Header::parse(image).map_err(ToolError::Image)?;
        let length = check_len(&header, u32::try_from(image.len()).unwrap_or(u32::MAX));
        let area = image.get(SIGNED_LEN..HEADER_BLOCK);
        let padding_ok = area.is_some_and(|p| header.check_notes(p).is_ok());
        let notes = area
            .filter(|_| padding_ok && header.notes_hash.is_some())
            .and_then(crate::notes_text)
            .map(str::to_owned);
        let payload_ok = image
            .get(HEADER_BLOCK..HEADER_BLOCK + header.payload_len as usize)
            .is_some_and(|p| header.check_payload(&Hasher::digest(p)).is_ok());
        let signature = key.map(|k| {
            if header.key_id != k.id() {
                return Err(ImageError::UnknownKey);
            }
            let sig = image
                .get(field::SIGNATURE)
                .and_then(|s| <[u8; SIGNATURE_LEN]>::try_from(s).ok())
                .ok_or(ImageError::Truncated {
                    need: SIGNED_LEN as u32,
                    got: image.len() as u32,
                })?;
            k.verify(&image[..HEADER_LEN], &sig)
        });
        Ok(Inspection {
            header,
            length,
            padding_ok,
            notes,
            payload_ok,
            signature,
        })
    }

    /// True when every check made passed (the signature only if a key was given).
    pub fn is_good(&self) -> bool {
        self.length.is_ok()
            && self.padding_ok
            && self.payload_ok
            && !matches!(self.signature, Some(Err(_)))
    }
}

impl fmt::Display for Inspection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let h = &self.header;
        let ok = |b: bool| if b { "ok" } else { "BAD" };
        writeln!(f, "board         {} ({:#06x})", h.board, h.board.0)?;
        writeln!(f, "version       {}", h.version)?;
        writeln!(f, "protocol      {}.{}", h.protocol.0, h.protocol.1)?;
        writeln!(
            f,
            "payload       {} bytes at {:#010x}",
            h.payload_len, h.load_addr
        )?;
        writeln!(f, "image         {} bytes", h.image_len())?;
        writeln!(f, "sha512        {}", h.payload_hash)?;
        writeln!(f, "image id      {:08x}", h.image_id())?;
        writeln!(f, "key id        {}", h.key_id)?;
        match &self.length {
            Ok(()) => writeln!(f, "length        ok")?,
            Err(e) => writeln!(f, "length        BAD: {e}")?,
        }
        writeln!(f, "notes area    {}", ok(self.padding_ok))?;
        if let Some(n) = &self.notes {
            writeln!(f, "release notes {}", n.replace('\n', "\n              "))?;
        }
        writeln!(f, "payload hash  {}", ok(self.payload_ok))?;
        match &self.signature {
            None => writeln!(f, "signature     not checked (give the public key)"),
            Some(Ok(())) => writeln!(f, "signature     ok"),
            Some(Err(e)) => writeln!(f, "signature     BAD: {e}"),
        }
    }
}
