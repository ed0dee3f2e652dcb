//! Templates at rest: envelope encryption with ChaCha20-Poly1305 (RustCrypto), independent of the
//! database, so that any backend stores the same sealed bytes.
//!
//! - A **master key** (32 bytes) comes from the key file ([`KeyRing::parse`]); its id is the first
//!   8 bytes of a SHA-256 of the key, in hex, so a row names the key that wrapped it without
//!   revealing it.
//! - Each subject has its own random **data key**, stored wrapped (sealed) by a master key next to
//!   the master key's id. The wrapping binds the subject id as associated data: a wrapped key
//!   copied to another subject does not open.
//! - Each template vector is sealed under its subject's data key with a fresh random nonce; the
//!   associated data binds the subject id, the model version and the dimension, so a row moved to
//!   another subject or altered in any of these is refused, not scored.
//!
//! Rotating the master key re-wraps the data keys only (templates stay as they are). Deleting a
//! subject deletes its wrapped data key, so a sealed template left behind without it (a free page,
//! a dead PostgreSQL tuple) cannot be opened. A copy of the database made *before* the deletion (a
//! backup) still holds the subject's wrapped data key next to its templates, and opens with the
//! master key that wrapped it: such copies are erased only once that master key is retired (rotated
//! away with `facegate rekey`, then destroyed). docs/storage.md, "Erasure: what it covers".
//!
//! Sealed bytes: a 12-byte nonce, then the ciphertext, then the 16-byte Poly1305 tag.

use chacha20poly1305::aead::{Aead, KeyInit, Payload};
use chacha20poly1305::{ChaCha20Poly1305, Key, Nonce};
use rand::RngCore;
use sha2::{Digest, Sha256};

/// Bytes of a master or data key.
pub const KEY_LEN: usize = 32;
const NONCE_LEN: usize = 12;
const TAG_LEN: usize = 16;
/// Bytes a sealed value has beyond its plaintext (nonce and tag).
pub const SEAL_OVERHEAD: usize = NONCE_LEN + TAG_LEN;

const TEMPLATE_CONTEXT: &[u8] = b"facegate template v1\0";
const DATA_KEY_CONTEXT: &[u8] = b"facegate data key v1\0";
const KEY_ID_CONTEXT: &[u8] = b"facegate template key id v1\0";

/// Why sealed bytes or a key file cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CipherError {
    #[error("the template key file is invalid: {0}")]
    KeyFile(String),
    #[error("the data key is wrapped by the master key {0}, which is not in the key file")]
    UnknownKey(String),
    #[error("authentication failed: the sealed bytes were altered, moved to another subject or sealed under another key")]
    Authentication,
}

/// A master key and its id.
#[derive(Clone)]
struct MasterKey {
    id: String,
    cipher: ChaCha20Poly1305,
}

/// The master keys: the current one (wraps new data keys) first, then older ones that still open
/// data keys wrapped before a rotation.
#[derive(Clone)]
pub struct KeyRing {
    keys: Vec<MasterKey>,
}

impl std::fmt::Debug for KeyRing {
    /// Ids only: the keys never reach a log.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KeyRing").field("ids", &self.keys.iter().map(|k| k.id.as_str()).collect::<Vec<_>>()).finish()
    }
}

/// The id of a master key: 16 hex digits of a SHA-256 of the key.
pub fn key_id(key: &[u8; KEY_LEN]) -> String {
    let mut hash = Sha256::new();
    hash.update(KEY_ID_CONTEXT);
    hash.update(key);
    hex::encode(&hash.finalize()[..8])
}

impl KeyRing {
    /// The keys, current first; refused when empty or when a key appears twice.
    pub fn new(keys: &[[u8; KEY_LEN]]) -> Result<KeyRing, CipherError> {
        if keys.is_empty() {
            return Err(CipherError::KeyFile("no key".into()));
        }
        let keys: Vec<MasterKey> =
            keys.iter().map(|k| MasterKey { id: key_id(k), cipher: ChaCha20Poly1305::new(Key::from_slice(k)) }).collect();
        for (i, k) in keys.iter().enumerate() {
            if keys[..i].iter().any(|other| other.id == k.id) {
                return Err(CipherError::KeyFile(format!("key {} is listed twice", k.id)));
            }
        }
        Ok(KeyRing { keys })
    }

    /// The key file: one key per line as 64 hex digits (32 bytes), the current key first, then
    /// any older keys still to be read; blank lines and lines starting with `#` are ignored.
    pub fn parse(text: &str) -> Result<KeyRing, CipherError> {
        let mut keys = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let mut key = [0u8; KEY_LEN];
            hex::decode_to_slice(line, &mut key)
                .map_err(|_| CipherError::KeyFile(format!("line {} is not 64 hex digits (a 32-byte key)", n + 1)))?;
            keys.push(key);
        }
        KeyRing::new(&keys)
    }

    /// The id of the current key (the one new data keys are wrapped with).
    pub fn current_id(&self) -> &str {
        &self.keys[0].id
    }

    /// A fresh random data key for `subject`, and its wrapping by the current key.
    pub fn new_data_key(&self, subject: &str) -> (DataKey, Vec<u8>) {
        let mut key = [0u8; KEY_LEN];
        rand::rng().fill_bytes(&mut key);
        let data_key = DataKey::new(key);
        let wrapped = self.wrap(&data_key, subject);
        (data_key, wrapped)
    }

    /// `data_key` wrapped by the current key for `subject`.
    pub fn wrap(&self, data_key: &DataKey, subject: &str) -> Vec<u8> {
        seal(&self.keys[0].cipher, &data_key_aad(subject), &data_key.key)
    }

    /// Open the data key of `subject` wrapped by the key `key_id`.
    pub fn unwrap(&self, subject: &str, key_id: &str, wrapped: &[u8]) -> Result<DataKey, CipherError> {
        let master = self.keys.iter().find(|k| k.id == key_id).ok_or_else(|| CipherError::UnknownKey(key_id.to_string()))?;
        let key: [u8; KEY_LEN] =
            open(&master.cipher, &data_key_aad(subject), wrapped)?.try_into().map_err(|_| CipherError::Authentication)?;
        Ok(DataKey::new(key))
    }
}

/// One subject's data key.
pub struct DataKey {
    key: [u8; KEY_LEN],
    cipher: ChaCha20Poly1305,
}

impl DataKey {
    fn new(key: [u8; KEY_LEN]) -> DataKey {
        DataKey { cipher: ChaCha20Poly1305::new(Key::from_slice(&key)), key }
    }

    /// `vector` (little-endian f32s) sealed for `subject` and `model_version`.
    pub fn seal_template(&self, subject: &str, model_version: &str, vector: &[f32]) -> Vec<u8> {
        let plain: Vec<u8> = vector.iter().flat_map(|v| v.to_le_bytes()).collect();
        seal(&self.cipher, &template_aad(subject, model_version, vector.len()), &plain)
    }

    /// The vector of a sealed template, if it is intact and belongs to `subject`, `model_version`
    /// and `dimension`.
    pub fn open_template(&self, subject: &str, model_version: &str, dimension: usize, sealed: &[u8]) -> Result<Vec<f32>, CipherError> {
        let plain = open(&self.cipher, &template_aad(subject, model_version, dimension), sealed)?;
        if plain.len() != 4 * dimension {
            return Err(CipherError::Authentication);
        }
        Ok(plain.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }
}

impl Drop for DataKey {
    fn drop(&mut self) {
        // Best effort: the cipher's own copy is the crate's to clear.
        self.key = [0; KEY_LEN];
        std::hint::black_box(&self.key);
    }
}

/// Length-prefixed fields, so that no two different field lists give the same bytes.
fn aad(context: &[u8], fields: &[&[u8]]) -> Vec<u8> {
    let mut out = context.to_vec();
    for field in fields {
        out.extend_from_slice(&(field.len() as u32).to_le_bytes());
        out.extend_from_slice(field);
    }
    out
}

fn template_aad(subject: &str, model_version: &str, dimension: usize) -> Vec<u8> {
    aad(TEMPLATE_CONTEXT, &[subject.as_bytes(), model_version.as_bytes(), &(dimension as u32).to_le_bytes()])
}

fn data_key_aad(subject: &str) -> Vec<u8> {
    aad(DATA_KEY_CONTEXT, &[subject.as_bytes()])
}

fn seal(cipher: &ChaCha20Poly1305, aad: &[u8], plain: &[u8]) -> Vec<u8> {
    let mut nonce = [0u8; NONCE_LEN];
    rand::rng().fill_bytes(&mut nonce);
    let sealed =
        cipher.encrypt(Nonce::from_slice(&nonce), Payload { msg: plain, aad }).expect("ChaCha20-Poly1305 seals any length used here");
    let mut out = Vec::with_capacity(NONCE_LEN + sealed.len());
    out.extend_from_slice(&nonce);
    out.extend_from_slice(&sealed);
    out
}

fn open(cipher: &ChaCha20Poly1305, aad: &[u8], sealed: &[u8]) -> Result<Vec<u8>, CipherError> {
    if sealed.len() < SEAL_OVERHEAD {
        return Err(CipherError::Authentication);
    }
    let (nonce, body) = sealed.split_at(NONCE_LEN);
    cipher.decrypt(Nonce::from_slice(nonce), Payload { msg: body, aad }).map_err(|_| CipherError::Authentication)
}

#[cfg(test)]
mod tests {
    use super::*;

    const K1: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";
    const K2: &str = "ff0102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1eff";

    #[test]
    fn key_files_list_the_current_key_first() {
        let ring = KeyRing::parse(&format!("# rotated 2026-11\n{K2}\n\n{K1}\n")).unwrap();
        let mut k2 = [0u8; KEY_LEN];
        hex::decode_to_slice(K2, &mut k2).unwrap();
        assert_eq!(ring.current_id(), key_id(&k2));
        assert_eq!(ring.current_id().len(), 16);
        assert!(!format!("{ring:?}").contains(K2), "the keys never show in Debug");
        for bad in ["", "# only a comment", "abcd", &format!("{K1}0"), &format!("{K1}\n{K1}"), &K1.replace('0', "g")] {
            assert!(matches!(KeyRing::parse(bad), Err(CipherError::KeyFile(_))), "{bad:?}");
        }
    }

    #[test]
    fn templates_open_only_for_their_subject_version_and_dimension() {
        let ring = KeyRing::parse(K1).unwrap();
        let (key, wrapped) = ring.new_data_key("alice");
        let vector = [0.6f32, -0.8, 0.0];
        let sealed = key.seal_template("alice", "v1", &vector);
        assert_eq!(sealed.len(), 12 + SEAL_OVERHEAD);
        assert_ne!(key.seal_template("alice", "v1", &vector), sealed, "a fresh nonce every time");
        assert_eq!(key.open_template("alice", "v1", 3, &sealed).unwrap(), vector);
        // The vector is not readable in the sealed bytes.
        let plain: Vec<u8> = vector.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert!(!sealed.windows(4).any(|w| w == &plain[..4]));
        for (subject, version, dims) in [("bob", "v1", 3), ("alice", "v2", 3), ("alice", "v1", 4)] {
            assert_eq!(key.open_template(subject, version, dims, &sealed), Err(CipherError::Authentication));
        }
        for i in [0, 12, sealed.len() - 1] {
            let mut flipped = sealed.clone();
            flipped[i] ^= 1;
            assert_eq!(key.open_template("alice", "v1", 3, &flipped), Err(CipherError::Authentication), "byte {i}");
        }
        assert_eq!(key.open_template("alice", "v1", 3, &sealed[..10]), Err(CipherError::Authentication));

        // The wrapped data key opens for its subject under its key only.
        let reopened = ring.unwrap("alice", ring.current_id(), &wrapped).unwrap();
        assert_eq!(reopened.open_template("alice", "v1", 3, &sealed).unwrap(), vector);
        assert!(matches!(ring.unwrap("bob", ring.current_id(), &wrapped), Err(CipherError::Authentication)));
        assert!(matches!(ring.unwrap("alice", "0000000000000000", &wrapped), Err(CipherError::UnknownKey(_))));
        let other = KeyRing::parse(K2).unwrap();
        assert!(other.unwrap("alice", ring.current_id(), &wrapped).is_err());

        // Rotation: the new ring (K2 current, K1 still readable) re-wraps the same data key.
        let rotated = KeyRing::parse(&format!("{K2}\n{K1}")).unwrap();
        let data_key = rotated.unwrap("alice", ring.current_id(), &wrapped).unwrap();
        let rewrapped = rotated.wrap(&data_key, "alice");
        let after = KeyRing::parse(K2).unwrap().unwrap("alice", rotated.current_id(), &rewrapped).unwrap();
        assert_eq!(after.open_template("alice", "v1", 3, &sealed).unwrap(), vector);
    }
}
