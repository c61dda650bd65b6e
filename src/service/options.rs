//! The processing options a client may send, and their conversion into the
//! engine's [`ProcessOptions`].

use serde::{Deserialize, Serialize};

use crate::bc1::Level;
use crate::pipeline::{AlphaOption, Format, Method, ProcessOptions, Resize, Target};
use crate::seam::erase::Mode;

/// Options as a client sends them (JSON part or query parameters); absent
/// ones take the command line's defaults.
///
/// An option is given or left out; `null` is refused, as the contract says.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobOptions {
    #[serde(default, deserialize_with = "present")]
    pub mode: Option<Mode>,
    #[serde(default, deserialize_with = "present")]
    pub method: Option<Method>,
    #[serde(default, deserialize_with = "present")]
    pub format: Option<Format>,
    #[serde(default, deserialize_with = "present")]
    pub bc1_level: Option<Level>,
    #[serde(default, deserialize_with = "present")]
    pub seam_aware: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    pub seam_weight: Option<f64>,
    #[serde(default, deserialize_with = "present")]
    pub mips: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    pub dx10: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    pub extra_maps: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    pub seam_tolerance: Option<f64>,
    #[serde(default, deserialize_with = "present")]
    pub erase_all: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    pub decoder: Option<Target>,
    #[serde(default, deserialize_with = "present")]
    pub resize: Option<Resize>,
    pub alpha: Option<AlphaOption>,
}

/// A field that, when present, must hold a value (not `null`).
fn present<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    T::deserialize(d).map(Some)
}

/// Every option decided: stored with the job, shown to the client, and part
/// of the result-cache key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResolvedOptions {
    pub mode: Mode,
    pub method: Method,
    pub format: Format,
    pub bc1_level: Level,
    pub seam_aware: bool,
    pub seam_weight: f64,
    pub mips: bool,
    pub dx10: bool,
    pub extra_maps: bool,
    /// Absent in jobs stored before seams were judged: they keep the default.
    #[serde(default = "default_seam_tolerance")]
    pub seam_tolerance: f64,
    #[serde(default)]
    pub erase_all: bool,
    /// Absent in jobs stored before decoders were targeted: the default.
    #[serde(default)]
    pub decoder: Target,
    /// Absent in jobs stored before sizes were fitted: left alone, as then.
    #[serde(default = "resize_before_fitting")]
    pub resize: Resize,
    /// Absent in jobs stored before alpha was kept: dropped, as then.
    #[serde(default = "alpha_before_keeping")]
    pub alpha: AlphaOption,
}

fn alpha_before_keeping() -> AlphaOption {
    AlphaOption::Drop
}

fn resize_before_fitting() -> Resize {
    Resize::None
}

fn default_seam_tolerance() -> f64 {
    crate::pipeline::DEFAULT_SEAM_TOLERANCE
}

/// Query parameters that are options (the rest of the query is not).
pub const QUERY_OPTIONS: &[&str] = &[
    "mode",
    "method",
    "format",
    "bc1_level",
    "seam_aware",
    "seam_weight",
    "mips",
    "dx10",
    "extra_maps",
    "seam_tolerance",
    "erase_all",
    "decoder",
    "resize",
    "alpha",
];

impl JobOptions {
    /// Fields of `over` replace those of `self`.
    pub fn overridden_by(self, over: JobOptions) -> JobOptions {
        JobOptions {
            mode: over.mode.or(self.mode),
            method: over.method.or(self.method),
            format: over.format.or(self.format),
            bc1_level: over.bc1_level.or(self.bc1_level),
            seam_aware: over.seam_aware.or(self.seam_aware),
            seam_weight: over.seam_weight.or(self.seam_weight),
            mips: over.mips.or(self.mips),
            dx10: over.dx10.or(self.dx10),
            extra_maps: over.extra_maps.or(self.extra_maps),
            seam_tolerance: over.seam_tolerance.or(self.seam_tolerance),
            erase_all: over.erase_all.or(self.erase_all),
            decoder: over.decoder.or(self.decoder),
            resize: over.resize.or(self.resize),
            alpha: over.alpha.or(self.alpha),
        }
    }

    /// Sets one option from its query-parameter form.
    pub fn set_from_query(&mut self, key: &str, value: &str) -> Result<(), String> {
        fn word<T: serde::de::DeserializeOwned>(key: &str, value: &str) -> Result<T, String> {
            serde_json::from_value(serde_json::Value::String(value.to_string()))
                .map_err(|_| format!("{key}: {value:?} is not one of the allowed values"))
        }
        fn boolean(key: &str, value: &str) -> Result<bool, String> {
            match value {
                "true" | "1" | "yes" => Ok(true),
                "false" | "0" | "no" => Ok(false),
                _ => Err(format!("{key}: {value:?} is not true or false")),
            }
        }
        match key {
            "mode" => self.mode = Some(word(key, value)?),
            "method" => self.method = Some(word(key, value)?),
            "format" => self.format = Some(word(key, value)?),
            "bc1_level" => self.bc1_level = Some(word(key, value)?),
            "seam_aware" => self.seam_aware = Some(boolean(key, value)?),
            "mips" => self.mips = Some(boolean(key, value)?),
            "dx10" => self.dx10 = Some(boolean(key, value)?),
            "extra_maps" => self.extra_maps = Some(boolean(key, value)?),
            "erase_all" => self.erase_all = Some(boolean(key, value)?),
            "decoder" => self.decoder = Some(word(key, value)?),
            "resize" => self.resize = Some(word(key, value)?),
            "alpha" => self.alpha = Some(word(key, value)?),
            "seam_tolerance" => {
                self.seam_tolerance = Some(
                    value
                        .parse()
                        .map_err(|_| format!("seam_tolerance: {value:?} is not a number"))?,
                )
            }
            "seam_weight" => {
                self.seam_weight = Some(
                    value
                        .parse()
                        .map_err(|_| format!("seam_weight: {value:?} is not a number"))?,
                )
            }
            _ => return Err(format!("unknown option {key:?}")),
        }
        Ok(())
    }

    /// Fills in the defaults of `seamstress process` and checks the values.
    pub fn resolve(&self) -> Result<ResolvedOptions, String> {
        let d = ProcessOptions::default();
        let seam_weight = self.seam_weight.unwrap_or(d.seam_weight);
        if !(seam_weight.is_finite() && seam_weight >= 0.0) {
            return Err(format!(
                "seam_weight must be a non-negative number, not {seam_weight}"
            ));
        }
        let seam_tolerance = self.seam_tolerance.unwrap_or(d.seam_tolerance);
        if !(seam_tolerance.is_finite() && seam_tolerance >= 0.0) {
            return Err(format!(
                "seam_tolerance must be a non-negative number of levels, not {seam_tolerance}"
            ));
        }
        Ok(ResolvedOptions {
            mode: self.mode.unwrap_or(d.mode),
            method: self.method.unwrap_or(d.method),
            format: self.format.unwrap_or(d.format),
            bc1_level: self.bc1_level.unwrap_or(d.bc1_level),
            seam_aware: self.seam_aware.unwrap_or(d.seam_aware),
            seam_weight,
            mips: self.mips.unwrap_or(d.mips),
            dx10: self.dx10.unwrap_or(d.dx10),
            extra_maps: self.extra_maps.unwrap_or(false),
            seam_tolerance,
            erase_all: self.erase_all.unwrap_or(d.erase_all),
            decoder: self.decoder.unwrap_or(d.decoder),
            resize: self.resize.unwrap_or(d.resize),
            alpha: self.alpha.unwrap_or(d.alpha),
        })
    }
}

/// The engine's options for a job: the same types, one field each (the
/// load option `extra_maps` aside).
pub fn process_options(o: &ResolvedOptions) -> ProcessOptions {
    ProcessOptions {
        mode: o.mode,
        method: o.method,
        format: o.format,
        bc1_level: o.bc1_level,
        seam_aware: o.seam_aware,
        seam_weight: o.seam_weight,
        mips: o.mips,
        dx10: o.dx10,
        seam_tolerance: o.seam_tolerance,
        erase_all: o.erase_all,
        // The service always draws the seams picture.
        pictures: true,
        decoder: o.decoder,
        resize: o.resize,
        alpha: o.alpha,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_command_lines() {
        let r = JobOptions::default().resolve().unwrap();
        let p = process_options(&r);
        let d = ProcessOptions::default();
        assert_eq!(p.mode, d.mode);
        assert_eq!(p.method, d.method);
        assert_eq!(p.format, d.format);
        assert_eq!(p.bc1_level, d.bc1_level);
        assert_eq!(p.seam_aware, d.seam_aware);
        assert_eq!(p.seam_weight, d.seam_weight);
        assert_eq!((p.mips, p.dx10), (d.mips, d.dx10));
    }

    #[test]
    fn query_values_are_checked() {
        let mut o = JobOptions::default();
        o.set_from_query("mode", "global").unwrap();
        o.set_from_query("mips", "true").unwrap();
        o.set_from_query("bc1_level", "fast").unwrap();
        assert!(serde_json::from_str::<JobOptions>(r#"{"bc1_level": null}"#).is_err());
        assert_eq!(
            serde_json::from_str::<JobOptions>(r#"{"mips": true}"#)
                .unwrap()
                .mips,
            Some(true)
        );
        assert!(o.set_from_query("mode", "sideways").is_err());
        assert!(o.set_from_query("dx10", "maybe").is_err());
        assert!(o.set_from_query("colour", "red").is_err());
        let r = o.resolve().unwrap();
        assert_eq!(r.mode, Mode::Global);
        assert!(r.mips);
        assert_eq!(r.bc1_level, Level::Fast);
        o.seam_weight = Some(f64::NAN);
        assert!(o.resolve().is_err());
    }

    #[test]
    fn json_part_overrides_query() {
        let q = JobOptions {
            mode: Some(Mode::Global),
            dx10: Some(true),
            ..JobOptions::default()
        };
        let part: JobOptions = serde_json::from_str(r#"{"mode":"local"}"#).unwrap();
        let m = q.overridden_by(part);
        assert_eq!(m.mode, Some(Mode::Local));
        assert_eq!(m.dx10, Some(true));
        assert!(serde_json::from_str::<JobOptions>(r#"{"colour":1}"#).is_err());
    }
}
