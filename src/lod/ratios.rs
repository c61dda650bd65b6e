//! The `lod` option: the triangle ratios of the levels of detail.
//!
//! Job options are `Copy` (they are passed and stored by value), so the
//! ratios sit in a fixed array rather than a `Vec`.

use std::fmt;

use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::ser::{SerializeSeq, Serializer};
use serde::{Deserialize, Serialize};

/// The most levels one job makes: a chain of halvings from 1/2 reaches
/// 1/256 in eight, below what any simplifier keeps recognisable.
pub const MAX_LODS: usize = 8;

/// Up to [`MAX_LODS`] ratios, each in (0, 1), strictly decreasing: level
/// `k` (from 1) keeps about `ratios[k - 1]` of each mesh's triangles.
///
/// JSON: an array of numbers; also read from a comma-separated string
/// (`"0.5,0.25"`), the form a query parameter and a CLI flag give.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct LodRatios {
    ratios: [f64; MAX_LODS],
    len: u8,
}

/// Ratios that cannot be levels of detail.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("lod: {0}")]
pub struct RatiosError(String);

impl LodRatios {
    /// Checks and keeps `ratios`.
    pub fn new(ratios: &[f64]) -> Result<LodRatios, RatiosError> {
        if ratios.len() > MAX_LODS {
            return Err(RatiosError(format!(
                "{} ratios, at most {MAX_LODS} levels",
                ratios.len()
            )));
        }
        let mut out = LodRatios::default();
        for (k, &r) in ratios.iter().enumerate() {
            if !(r.is_finite() && r > 0.0 && r < 1.0) {
                return Err(RatiosError(format!(
                    "{r} is not a ratio of triangles between 0 and 1"
                )));
            }
            if k > 0 && r >= ratios[k - 1] {
                return Err(RatiosError(format!(
                    "ratios must decrease level by level ({} then {r})",
                    ratios[k - 1]
                )));
            }
            out.ratios[k] = r;
        }
        out.len = ratios.len() as u8;
        Ok(out)
    }

    /// The ratios, finest level first.
    pub fn as_slice(&self) -> &[f64] {
        &self.ratios[..usize::from(self.len)]
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl std::str::FromStr for LodRatios {
    type Err = RatiosError;

    /// Comma-separated ratios, in brackets or not (a query parameter
    /// holds the list as clients write it, `[0.5,0.25]` or `[]`); an empty
    /// list is no levels.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        let s = s
            .strip_prefix('[')
            .and_then(|inner| inner.strip_suffix(']'))
            .unwrap_or(s);
        let mut ratios = Vec::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            ratios.push(
                part.parse::<f64>()
                    .map_err(|_| RatiosError(format!("{part:?} is not a number")))?,
            );
        }
        LodRatios::new(&ratios)
    }
}

impl Serialize for LodRatios {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(self.as_slice().len()))?;
        for r in self.as_slice() {
            seq.serialize_element(r)?;
        }
        seq.end()
    }
}

impl<'de> Deserialize<'de> for LodRatios {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Ratios;
        impl<'de> Visitor<'de> for Ratios {
            type Value = LodRatios;

            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("an array of ratios or a comma-separated string of them")
            }

            fn visit_str<E: de::Error>(self, v: &str) -> Result<LodRatios, E> {
                v.parse().map_err(E::custom)
            }

            fn visit_f64<E: de::Error>(self, v: f64) -> Result<LodRatios, E> {
                LodRatios::new(&[v]).map_err(E::custom)
            }

            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<LodRatios, A::Error> {
                let mut ratios = Vec::new();
                while let Some(r) = seq.next_element::<f64>()? {
                    if ratios.len() == MAX_LODS {
                        return Err(de::Error::custom(format!("at most {MAX_LODS} levels")));
                    }
                    ratios.push(r);
                }
                LodRatios::new(&ratios).map_err(de::Error::custom)
            }
        }
        d.deserialize_any(Ratios)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ratios_read_from_arrays_and_strings() {
        let a: LodRatios = serde_json::from_str("[0.5, 0.25]").unwrap();
        let s: LodRatios = serde_json::from_str("\"0.5,0.25\"").unwrap();
        // As a query parameter carries the list a client sends.
        let q: LodRatios = serde_json::from_str("\"[0.5,0.25]\"").unwrap();
        assert_eq!(q, s);
        assert!(serde_json::from_str::<LodRatios>("\"[]\"")
            .unwrap()
            .is_empty());
        assert_eq!(a, s);
        assert_eq!(a.as_slice(), [0.5, 0.25]);
        assert_eq!(serde_json::to_string(&a).unwrap(), "[0.5,0.25]");
        assert!(serde_json::from_str::<LodRatios>("[0.25, 0.5]").is_err());
        assert!(serde_json::from_str::<LodRatios>("[1.5]").is_err());
        assert!(serde_json::from_str::<LodRatios>("\"half\"").is_err());
        assert!("".parse::<LodRatios>().unwrap().is_empty());
    }
}
