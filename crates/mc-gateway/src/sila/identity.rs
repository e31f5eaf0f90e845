//! The SiLA server's identity: its UUID, made once per island, and its name, which a client may
//! change; both kept in a small JSON file in the gateway's state directory.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::SilaError;

/// The longest server name SiLAService accepts, in characters.
pub const MAX_NAME: usize = 255;

/// What the file holds.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Identity {
    /// The server UUID (lower-case, hyphenated).
    pub uuid: String,
    /// The server name.
    pub name: String,
    /// The names the kept self-signed certificate was made for (it is made again when they change).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cert_names: Vec<String>,
}

impl Identity {
    /// A new identity named `name`, with a new random UUID.
    pub fn new(name: String) -> Identity {
        Identity {
            uuid: uuid::Uuid::new_v4().to_string(),
            name,
            cert_names: Vec::new(),
        }
    }

    /// Parses the file's text.
    pub fn parse(text: &str) -> Result<Identity, String> {
        let id: Identity = serde_json::from_str(text).map_err(|e| e.to_string())?;
        uuid::Uuid::parse_str(&id.uuid).map_err(|e| format!("uuid {:?}: {e}", id.uuid))?;
        check_name(&id.name)?;
        Ok(id)
    }
}

/// A server name SiLAService accepts: 1 to [`MAX_NAME`] characters.
pub fn check_name(name: &str) -> Result<(), String> {
    let n = name.chars().count();
    if n == 0 || n > MAX_NAME {
        return Err(format!(
            "a server name must be 1 to {MAX_NAME} characters; got {n}"
        ));
    }
    Ok(())
}

/// Where one island's identity is kept: `sila.json` in `dir`, or `sila-ISLAND.json` when the
/// gateway serves a named island (several gateways may share a state directory).
pub fn file(dir: &Path, island: Option<&str>) -> PathBuf {
    match island {
        Some(i) => dir.join(format!("sila-{i}.json")),
        None => dir.join("sila.json"),
    }
}

/// The identity kept in `path`, made (and kept, when the directory can be written) with
/// `default_name` the first time; a file that cannot be read or parsed is an error.
pub fn load_or_create(path: &Path, default_name: &str) -> Result<Identity, SilaError> {
    let err = |why: String| SilaError::Identity {
        path: path.to_owned(),
        why,
    };
    match std::fs::read_to_string(path) {
        Ok(text) => Identity::parse(&text).map_err(err),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let id = Identity::new(default_name.to_owned());
            // A state directory that cannot be written must not keep the gateway from running.
            if let Err(e) = save(path, &id) {
                tracing::warn!(error = %e, "SiLA server identity not kept: its UUID changes at every start");
            }
            Ok(id)
        }
        Err(e) => Err(err(e.to_string())),
    }
}

/// Keeps `id` in `path` (written beside it and renamed, so a crash leaves the old or the new file).
pub fn save(path: &Path, id: &Identity) -> Result<(), SilaError> {
    let err = |why: String| SilaError::Identity {
        path: path.to_owned(),
        why,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
    }
    let tmp = path.with_extension("json.new");
    let text = serde_json::to_string_pretty(id).map_err(|e| err(e.to_string()))?;
    std::fs::write(&tmp, text + "\n").map_err(|e| err(e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_identity_is_made_once_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = file(dir.path(), Some("bench-a"));
        assert!(path.ends_with("sila-bench-a.json"));
        let first = load_or_create(&path, "iHEX bench-a").unwrap();
        assert_eq!(first.name, "iHEX bench-a");
        let again = load_or_create(&path, "other").unwrap();
        assert_eq!(again, first, "the same UUID and name after a restart");
        let renamed = Identity {
            name: "Bench A".into(),
            ..first.clone()
        };
        save(&path, &renamed).unwrap();
        assert_eq!(load_or_create(&path, "x").unwrap(), renamed);
    }

    #[test]
    fn a_broken_file_is_an_error_not_a_new_identity() {
        let dir = tempfile::tempdir().unwrap();
        let path = file(dir.path(), None);
        std::fs::write(&path, r#"{"uuid":"nope","name":"x"}"#).unwrap();
        let e = load_or_create(&path, "x").unwrap_err().to_string();
        assert!(e.contains("uuid \"nope\""), "{e}");
        assert!(check_name("").is_err());
        assert!(check_name(&"n".repeat(256)).is_err());
        assert!(check_name("Bench").is_ok());
    }
}
