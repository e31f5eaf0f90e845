//! [`Retained`] as a fixed block of words for RAM that survives a system reset: magic, version,
//! payload, CRC-32. [`Retained::decode`] refuses anything else, so the garbage SRAM holds after a
//! power cut can never turn the relay on.

use ihex_proto::{DockPartner, NodeId, Port};

use super::Retained;

/// Words of an encoded [`Retained`] block: magic, version, relay + confirmed, one per port, CRC.
pub const RETAINED_WORDS: usize = 3 + Port::COUNT as usize + 1;

/// First word of a block ("iHEX relay kept").
const MAGIC: u32 = 0x1E7A_5E1A;
/// Layout version; a block of another version is refused (a firmware update may change it).
const VERSION: u32 = 1;
/// Bit of a link word saying a partner is present; the low 16 bits hold its node ID (an assignable
/// one, as the docking handshake gives), bits 16..24 its port.
const LINK_PRESENT: u32 = 1 << 31;

impl Retained {
    /// Words of an encoded block ([`Retained::encode`]).
    pub const WORDS: usize = RETAINED_WORDS;

    /// The block to leave in no-init RAM just before a reset the node asked for.
    pub fn encode(&self) -> [u32; RETAINED_WORDS] {
        let mut w = [0u32; RETAINED_WORDS];
        w[0] = MAGIC;
        w[1] = VERSION;
        w[2] = u32::from(self.relay) | u32::from(self.confirmed) << 8;
        for (slot, link) in w[3..3 + Port::COUNT as usize].iter_mut().zip(&self.links) {
            *slot = link.map_or(0, |p| {
                LINK_PRESENT | u32::from(p.node.get()) | u32::from(p.port.get()) << 16
            });
        }
        w[RETAINED_WORDS - 1] = crc32(&w[..RETAINED_WORDS - 1]);
        w
    }

    /// The [`Retained`] a block holds; `None` unless magic, version, CRC and every field are
    /// exactly what [`Retained::encode`] writes.
    pub fn decode(w: &[u32; RETAINED_WORDS]) -> Option<Self> {
        if w[0] != MAGIC
            || w[1] != VERSION
            || w[RETAINED_WORDS - 1] != crc32(&w[..RETAINED_WORDS - 1])
        {
            return None;
        }
        if w[2] & !0xFF01 != 0 {
            return None;
        }
        let mut links = [None; Port::COUNT as usize];
        for (link, &word) in links.iter_mut().zip(&w[3..3 + Port::COUNT as usize]) {
            *link = match word {
                0 => None,
                _ if word & LINK_PRESENT != 0 && word & 0x7F00_0000 == 0 => Some(DockPartner {
                    node: NodeId::new_sc((word & 0xFFFF) as u16)?,
                    port: Port::new((word >> 16) as u8)?,
                }),
                _ => return None,
            };
        }
        Some(Retained {
            relay: w[2] & 1 != 0,
            confirmed: (w[2] >> 8) as u8,
            links,
        })
    }
}

/// CRC-32 (IEEE 802.3, reflected, as zlib) over the words' little-endian bytes. Bitwise: the block is
/// a few dozen bytes, once per reset, and a table would cost 1 KiB of flash in the bootloader.
fn crc32(words: &[u32]) -> u32 {
    let mut crc = !0u32;
    for byte in words.iter().flat_map(|w| w.to_le_bytes()) {
        crc ^= u32::from(byte);
        for _ in 0..8 {
            crc = (crc >> 1) ^ (0xEDB8_8320 & (crc & 1).wrapping_neg());
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sample() -> Retained {
        let mut links = [None; Port::COUNT as usize];
        links[0] = Some(DockPartner {
            node: NodeId::new(0x002).unwrap(),
            port: Port::new(3).unwrap(),
        });
        links[5] = Some(DockPartner {
            node: NodeId::new(0xFFD).unwrap(),
            port: Port::new(7).unwrap(),
        });
        Retained {
            relay: true,
            confirmed: 0b10_0001,
            links,
        }
    }

    #[test]
    fn crc32_is_the_ieee_one() {
        // The standard check value of CRC-32/ISO-HDLC is over "123456789"; over whole words we
        // check "1234" + "5678" against zlib's value for those 8 bytes.
        let w = [u32::from_le_bytes(*b"1234"), u32::from_le_bytes(*b"5678")];
        assert_eq!(crc32(&w), 0x9AE0_DAAF);
    }

    #[test]
    fn golden_block() {
        let w = sample().encode();
        assert_eq!(w[0], 0x1E7A_5E1A);
        assert_eq!(w[1], 1);
        assert_eq!(w[2], 0x2101);
        assert_eq!(w[3], 0x8003_0002);
        assert_eq!(w[8], 0x8007_0FFD);
        assert_eq!(w[4], 0);
        assert_eq!(Retained::decode(&w), Some(sample()));
    }

    #[test]
    fn refuses_wrong_magic_version_crc_and_fields() {
        let good = sample().encode();
        for i in 0..RETAINED_WORDS {
            for bit in 0..32 {
                let mut w = good;
                w[i] ^= 1 << bit;
                assert_eq!(Retained::decode(&w), None, "word {i} bit {bit}");
            }
        }
        // A block with a valid CRC but a field encode never writes.
        let mut w = good;
        w[2] |= 0x10;
        w[RETAINED_WORDS - 1] = crc32(&w[..RETAINED_WORDS - 1]);
        assert_eq!(Retained::decode(&w), None);
        let mut w = good;
        w[4] = LINK_PRESENT | 0xFFF; // node ID 0xFFF means none on the wire: not a partner
        w[RETAINED_WORDS - 1] = crc32(&w[..RETAINED_WORDS - 1]);
        assert_eq!(Retained::decode(&w), None);
        let mut w = good;
        w[1] = 2;
        w[RETAINED_WORDS - 1] = crc32(&w[..RETAINED_WORDS - 1]);
        assert_eq!(Retained::decode(&w), None);
        assert_eq!(Retained::decode(&[0; RETAINED_WORDS]), None);
        assert_eq!(Retained::decode(&[u32::MAX; RETAINED_WORDS]), None);
    }

    fn retained() -> impl Strategy<Value = Retained> {
        let link = proptest::option::of((1u16..=0xFFD, 0u8..8)).prop_map(|l| {
            l.map(|(n, p)| DockPartner {
                node: NodeId::new(n).unwrap(),
                port: Port::new(p).unwrap(),
            })
        });
        (any::<bool>(), any::<u8>(), proptest::array::uniform8(link)).prop_map(
            |(relay, confirmed, links)| Retained {
                relay,
                confirmed,
                links,
            },
        )
    }

    proptest! {
        #[test]
        fn round_trip(r in retained()) {
            prop_assert_eq!(Retained::decode(&r.encode()), Some(r));
        }

        // Random RAM decodes only if it happens to carry the magic, the version and a matching
        // CRC: about 2^-96, never in a test run.
        #[test]
        fn random_words_never_decode(w in proptest::array::uniform12(any::<u32>())) {
            prop_assert_eq!(Retained::decode(&w), None);
        }

        // Even with the right magic and version, a random payload needs its CRC (2^-32).
        #[test]
        fn random_payload_with_magic_never_decodes(w in proptest::array::uniform12(any::<u32>())) {
            let mut w = w;
            w[0] = MAGIC;
            w[1] = VERSION;
            prop_assert_eq!(Retained::decode(&w), None);
        }
    }
}
