//! A minimal .usdz writer: an uncompressed (stored) zip whose file data all start on 64-byte
//! boundaries, the root USD layer first (the USDZ specification's packaging rules).

/// One file in the package: its path inside the zip and its bytes.
pub struct Entry<'a> {
    pub name: &'a str,
    pub data: &'a [u8],
}

fn u16le(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_le_bytes());
}
fn u32le(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

/// Build the package bytes. Entries are written in order (the root layer must come first).
pub fn usdz_bytes(entries: &[Entry<'_>]) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    for e in entries {
        if e.data.len() > u32::MAX as usize || out.len() > u32::MAX as usize {
            return Err(format!("{} is too large for a zip without ZIP64", e.name));
        }
        let ext = e.name.rsplit('.').next().unwrap_or("").to_ascii_lowercase();
        if !["usda", "usdc", "usd", "png", "jpg", "jpeg", "exr"].contains(&ext.as_str()) {
            return Err(format!("{}: file type not allowed in a usdz", e.name));
        }
        let crc = crc32fast::hash(e.data);
        let offset = out.len() as u32;
        let name = e.name.as_bytes();
        // Pad with an extra field so the data starts on a 64-byte boundary.
        let unpadded = out.len() + 30 + name.len();
        let mut pad = (64 - unpadded % 64) % 64;
        if pad != 0 && pad < 4 {
            pad += 64;
        }
        u32le(&mut out, 0x0403_4b50);
        u16le(&mut out, 20); // version needed
        u16le(&mut out, 0); // flags
        u16le(&mut out, 0); // stored
        u16le(&mut out, 0); // mod time
        u16le(&mut out, 0x21); // mod date (1980-01-01)
        u32le(&mut out, crc);
        u32le(&mut out, e.data.len() as u32);
        u32le(&mut out, e.data.len() as u32);
        u16le(&mut out, name.len() as u16);
        u16le(&mut out, pad as u16);
        out.extend_from_slice(name);
        if pad > 0 {
            u16le(&mut out, 0x1986); // private padding field id
            u16le(&mut out, (pad - 4) as u16);
            out.resize(out.len() + pad - 4, 0);
        }
        debug_assert_eq!(out.len() % 64, 0);
        out.extend_from_slice(e.data);

        u32le(&mut central, 0x0201_4b50);
        u16le(&mut central, 20); // version made by
        u16le(&mut central, 20);
        u16le(&mut central, 0);
        u16le(&mut central, 0);
        u16le(&mut central, 0);
        u16le(&mut central, 0x21);
        u32le(&mut central, crc);
        u32le(&mut central, e.data.len() as u32);
        u32le(&mut central, e.data.len() as u32);
        u16le(&mut central, name.len() as u16);
        u16le(&mut central, 0); // extra
        u16le(&mut central, 0); // comment
        u16le(&mut central, 0); // disk
        u16le(&mut central, 0); // internal attrs
        u32le(&mut central, 0); // external attrs
        u32le(&mut central, offset);
        central.extend_from_slice(name);
    }
    let cd_offset = out.len() as u32;
    let cd_len = central.len() as u32;
    out.extend_from_slice(&central);
    u32le(&mut out, 0x0605_4b50);
    u16le(&mut out, 0);
    u16le(&mut out, 0);
    u16le(&mut out, entries.len() as u16);
    u16le(&mut out, entries.len() as u16);
    u32le(&mut out, cd_len);
    u32le(&mut out, cd_offset);
    u16le(&mut out, 0);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_are_64_byte_aligned_and_stored() {
        let a = b"#usda 1.0\n".to_vec();
        let b = vec![7u8; 1000];
        let z = usdz_bytes(&[
            Entry {
                name: "asset.usda",
                data: &a,
            },
            Entry {
                name: "textures/x.png",
                data: &b,
            },
        ])
        .unwrap();
        for (data, name) in [(&a, "asset.usda"), (&b, "textures/x.png")] {
            let at = z.windows(data.len()).position(|w| w == &data[..]).unwrap();
            assert_eq!(at % 64, 0, "{name} at {at}");
        }
        assert_eq!(&z[..4], b"PK\x03\x04");
        assert_eq!(&z[z.len() - 22..z.len() - 18], b"PK\x05\x06");
        assert!(usdz_bytes(&[Entry {
            name: "a.txt",
            data: b"x"
        }])
        .is_err());
    }
}
