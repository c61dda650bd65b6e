//! The 128 bits of a BC7 block, least significant bit of byte 0 first.

/// Reads fields in order from a block.
pub struct BitReader {
    bits: u128,
    at: u32,
}

impl BitReader {
    pub fn new(bytes: &[u8; 16]) -> Self {
        BitReader {
            bits: u128::from_le_bytes(*bytes),
            at: 0,
        }
    }

    /// The next `n` (≤ 8) bits; zeros past the end.
    #[inline]
    pub fn read(&mut self, n: u32) -> u8 {
        if n == 0 || self.at >= 128 {
            self.at += n;
            return 0;
        }
        let v = (self.bits >> self.at) as u8 & (((1u16 << n) - 1) as u8);
        self.at += n;
        v
    }

    #[cfg(test)]
    pub fn position(&self) -> u32 {
        self.at
    }
}

/// Appends fields in order to a block.
#[derive(Default)]
pub struct BitWriter {
    bits: u128,
    at: u32,
}

impl BitWriter {
    /// Appends the low `n` bits of `v`; bits past 128 are dropped.
    #[inline]
    pub fn write(&mut self, v: u32, n: u32) {
        if n > 0 && self.at < 128 {
            let mask = (1u128 << n) - 1;
            self.bits |= (u128::from(v) & mask) << self.at;
        }
        self.at += n;
    }

    pub fn position(&self) -> u32 {
        self.at
    }

    pub fn bytes(&self) -> [u8; 16] {
        self.bits.to_le_bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_round_trip() {
        let mut w = BitWriter::default();
        let fields = [(1, 1), (5, 3), (0x7f, 7), (0, 2), (0xff, 8)];
        for &(v, n) in &fields {
            w.write(v, n);
        }
        let mut r = BitReader::new(&w.bytes());
        for &(v, n) in &fields {
            assert_eq!(u32::from(r.read(n)), v);
        }
        assert_eq!(r.position(), w.position());
    }
}
