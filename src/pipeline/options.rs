//! A job's options, defined once: the pipeline reads them, the CLI builds
//! them from its flags, the service from a request's query and JSON part
//! (an [`OptionPatch`] over the defaults), the job store keeps them, the
//! report and the caches key on their JSON form.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::bc1::{Level, Target};
use crate::lod::LodRatios;
use crate::resize::Resize;
use crate::seam::erase::Mode;

use super::alpha::AlphaOption;

pub use crate::bc1::seam_aware::DEFAULT_ALPHA as DEFAULT_SEAM_WEIGHT;
pub use crate::seam::classify::DEFAULT_TOLERANCE as DEFAULT_SEAM_TOLERANCE;

/// How seams are removed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Both sides agree along the whole seam, integrated exactly
    // (SPEC §4).
    #[default]
    Erase,
    /// Both sides agree at points sampled along the seams
    // (the seeds' baseline, a simpler least-squares).
    Masking,
}

/// What `process` writes for each texture besides the erased PNG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    /// BC1 (BC3 or BC1 with one-bit alpha where alpha is kept). `dds` is
    /// its name from before BC7, when the format and the file were one.
    #[default]
    #[serde(alias = "dds")]
    Bc1,
    /// BC7, colour and alpha in one format.
    Bc7,
    /// The erased PNG only.
    Png,
}

impl Format {
    /// Whether the format writes a block-compressed file.
    pub fn compressed(self) -> bool {
        self != Format::Png
    }
}

/// The file block-compressed textures are written in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Container {
    /// DirectDraw Surface, referenced from the rewritten model through
    /// `MSFT_texture_dds`.
    #[default]
    Dds,
    /// KTX 2.0, optionally Zstandard-supercompressed (`zstd`).
    Ktx2,
}

/// The highest Zstandard level.
pub const MAX_ZSTD_LEVEL: u8 = 22;

/// Every option of a job, decided.
///
/// A field absent from stored JSON takes the value jobs had before the
/// option existed (so a stored job keeps its meaning); a new job starts
/// from [`ProcessOptions::default`], which is `seamstress process`'s.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessOptions {
    pub mode: Mode,
    pub method: Method,
    pub format: Format,
    pub bc1_level: Level,
    /// BC7 encoder effort (with `format` `bc7`).
    #[serde(default)]
    pub bc7_level: Level,
    /// The file the blocks are written in.
    #[serde(default)]
    pub container: Container,
    /// Zstandard supercompression level of a KTX2 file, 1–22; 0 for none.
    #[serde(default)]
    pub zstd: u8,
    pub seam_aware: bool,
    pub seam_weight: f64,
    /// Write the whole mip chain, each level erased and encoded on its own.
    /// On by default, as the usual compressors write it: a single level
    /// aliases wherever the texture is drawn smaller than its size.
    pub mips: bool,
    pub dx10: bool,
    /// Also process occlusion and metallic-roughness textures.
    #[serde(default)]
    pub extra_maps: bool,
    /// Seams whose sides, as their own charts paint them, differ by more
    /// than this (8-bit levels, RMS along the edge) are left as painted.
    #[serde(default = "default_seam_tolerance")]
    pub seam_tolerance: f64,
    /// Close every seam, however far apart its sides are painted.
    #[serde(default)]
    pub erase_all: bool,
    /// The GPU decoders the seam-aware encoding keeps the seams closed under.
    #[serde(default)]
    pub decoder: Target,
    /// What happens to a texture whose sides are not multiples of 4.
    #[serde(default = "resize_before_fitting")]
    pub resize: Resize,
    /// What the DDS keeps of alpha.
    #[serde(default = "alpha_before_keeping")]
    pub alpha: AlphaOption,
    /// Draw `<name>.seams.png` for each texture, and write what the view
    /// page draws the seams and the discarded filter taps from
    /// (`<name>.charts.png`, `<name>.edges.json`).
    #[serde(default = "pictures_before_option")]
    pub pictures: bool,
    /// Seam-aware levels of detail: the ratios of each mesh's triangles
    /// that the rewritten model carries (`MSFT_lod`); none by default.
    #[serde(default)]
    pub lod: LodRatios,
    /// Also write each level of detail as its own `<name>.lodN.glb`.
    #[serde(default)]
    pub lod_files: bool,
    /// Also write the regular BC1 encoding of level 0 as
    /// `<name>.regular.dds`, for the view page to show beside the
    /// seam-aware one.
    #[serde(default)]
    pub keep_regular: bool,
}

fn default_seam_tolerance() -> f64 {
    DEFAULT_SEAM_TOLERANCE
}

fn resize_before_fitting() -> Resize {
    Resize::None
}

fn alpha_before_keeping() -> AlphaOption {
    AlphaOption::Drop
}

/// Jobs stored before this was an option always drew their pictures.
fn pictures_before_option() -> bool {
    true
}

impl Default for ProcessOptions {
    fn default() -> Self {
        ProcessOptions {
            mode: Mode::Local,
            method: Method::Erase,
            format: Format::Bc1,
            bc1_level: Level::Default,
            bc7_level: Level::Default,
            container: Container::Dds,
            zstd: 0,
            seam_aware: true,
            seam_weight: DEFAULT_SEAM_WEIGHT,
            mips: true,
            dx10: false,
            extra_maps: false,
            seam_tolerance: DEFAULT_SEAM_TOLERANCE,
            erase_all: false,
            decoder: Target::Robust,
            resize: Resize::Mul4,
            alpha: AlphaOption::Auto,
            pictures: false,
            lod: LodRatios::default(),
            lod_files: false,
            keep_regular: false,
        }
    }
}

/// An option given a value it cannot take, or one that does not exist.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct OptionsError(String);

impl ProcessOptions {
    /// The defaults of a service job: those of `seamstress process`, with
    /// the seams picture drawn (a client downloads what it wants).
    pub fn service_default() -> ProcessOptions {
        ProcessOptions {
            pictures: true,
            ..ProcessOptions::default()
        }
    }

    /// Checks what the types do not: the numbers' ranges.
    pub fn validate(&self) -> Result<(), OptionsError> {
        let non_negative = |name: &str, v: f64, what: &str| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(OptionsError(format!(
                    "{name} must be a non-negative {what}, not {v}"
                )))
            }
        };
        non_negative("seam_weight", self.seam_weight, "number")?;
        non_negative("seam_tolerance", self.seam_tolerance, "number of levels")?;
        if self.lod_files && self.lod.is_empty() {
            return Err(OptionsError(
                "lod_files writes the levels of detail: it needs lod".into(),
            ));
        }
        if self.zstd > MAX_ZSTD_LEVEL {
            return Err(OptionsError(format!(
                "zstd must be a Zstandard level from 1 to {MAX_ZSTD_LEVEL} (0: none), not {}",
                self.zstd
            )));
        }
        if self.zstd > 0 && self.container != Container::Ktx2 {
            return Err(OptionsError(
                "zstd supercompresses KTX2 files: it needs container ktx2".into(),
            ));
        }
        if self.format == Format::Bc7 && matches!(self.alpha, AlphaOption::Bc1a | AlphaOption::Bc3)
        {
            return Err(OptionsError(format!(
                "alpha {}: that is a BC1 choice; BC7 keeps alpha in its own blocks \
                 (alpha auto) or drops it (alpha drop)",
                serde_json::to_value(self.alpha).unwrap_or_default()
            )));
        }
        Ok(())
    }

    /// The options' JSON object, the form every cache and the report key on.
    pub fn to_json(&self) -> Map<String, Value> {
        match serde_json::to_value(self) {
            Ok(Value::Object(map)) => map,
            // A struct of plain fields always serialises to an object.
            _ => Map::new(),
        }
    }

    /// Whether `name` is an option.
    pub fn is_option(name: &str) -> bool {
        ProcessOptions::default().to_json().contains_key(name)
    }
}

/// Some options given, as a request holds them before the defaults: a
/// JSON object whose every key is an option and whose every value fits it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OptionPatch(Map<String, Value>);

impl OptionPatch {
    /// A JSON object of options; `null` is refused (an option is given or
    /// left out).
    pub fn from_json(text: &[u8]) -> Result<OptionPatch, OptionsError> {
        match serde_json::from_slice::<Value>(text) {
            Ok(Value::Object(map)) => {
                let mut patch = OptionPatch::default();
                for (key, value) in map {
                    patch.set(key, value)?;
                }
                Ok(patch)
            }
            Ok(_) => Err(OptionsError("the options must be a JSON object".into())),
            Err(e) => Err(OptionsError(format!("the options are not JSON: {e}"))),
        }
    }

    /// Sets one option from its query-parameter form: the value is read as
    /// the option's type (`true`/`false`, a number, or a word).
    pub fn set_from_query(&mut self, key: &str, value: &str) -> Result<(), OptionsError> {
        let typed = match ProcessOptions::default().to_json().get(key) {
            None => return Err(OptionsError(format!("unknown option {key:?}"))),
            Some(Value::Bool(_)) => match value {
                "true" | "1" | "yes" => Value::Bool(true),
                "false" | "0" | "no" => Value::Bool(false),
                _ => {
                    return Err(OptionsError(format!(
                        "{key}: {value:?} is not true or false"
                    )))
                }
            },
            // A whole number stays one, for the options that take only
            // those (`zstd`).
            Some(Value::Number(_)) => value
                .parse::<u64>()
                .ok()
                .map(serde_json::Number::from)
                .or_else(|| {
                    value
                        .parse::<f64>()
                        .ok()
                        .and_then(serde_json::Number::from_f64)
                })
                .map(Value::Number)
                .ok_or_else(|| OptionsError(format!("{key}: {value:?} is not a number")))?,
            Some(_) => Value::String(value.to_string()),
        };
        self.set(key.to_string(), typed)
    }

    /// Sets one option, checking its name and that the value fits it.
    fn set(&mut self, key: String, value: Value) -> Result<(), OptionsError> {
        let mut trial = ProcessOptions::default().to_json();
        if !trial.contains_key(&key) {
            return Err(OptionsError(format!("unknown option {key:?}")));
        }
        if value.is_null() {
            return Err(OptionsError(format!("{key}: null is not a value")));
        }
        trial.insert(key.clone(), value.clone());
        serde_json::from_value::<ProcessOptions>(Value::Object(trial))
            .map_err(|e| OptionsError(format!("{key}: {value} is not allowed ({e})")))?;
        self.0.insert(key, value);
        Ok(())
    }

    /// Options of `over` replace those of `self`.
    pub fn overridden_by(mut self, over: OptionPatch) -> OptionPatch {
        self.0.extend(over.0);
        self
    }

    /// The patch over `base`, checked.
    pub fn resolve(&self, base: &ProcessOptions) -> Result<ProcessOptions, OptionsError> {
        let mut all = base.to_json();
        all.extend(self.0.clone());
        let options: ProcessOptions = serde_json::from_value(Value::Object(all))
            .map_err(|e| OptionsError(format!("the options: {e}")))?;
        options.validate()?;
        Ok(options)
    }
}

impl From<&ProcessOptions> for OptionPatch {
    /// Every option given: a client sends its resolved options whole.
    fn from(options: &ProcessOptions) -> OptionPatch {
        OptionPatch(options.to_json())
    }
}

impl Serialize for OptionPatch {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.0.serialize(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_values_take_the_options_types() {
        let mut o = OptionPatch::default();
        o.set_from_query("mode", "global").unwrap();
        o.set_from_query("mips", "false").unwrap();
        o.set_from_query("bc1_level", "fast").unwrap();
        o.set_from_query("format", "bc7").unwrap();
        o.set_from_query("container", "ktx2").unwrap();
        o.set_from_query("zstd", "19").unwrap();
        assert!(o.set_from_query("container", "zip").is_err());
        assert!(o.set_from_query("zstd", "1.5").is_err());
        o.set_from_query("seam_weight", "12.5").unwrap();
        assert!(o.set_from_query("mode", "sideways").is_err());
        assert!(o.set_from_query("dx10", "maybe").is_err());
        assert!(o.set_from_query("seam_tolerance", "wide").is_err());
        assert!(o.set_from_query("colour", "red").is_err());
        o.set_from_query("lod", "0.5,0.25").unwrap();
        assert!(o.clone().set_from_query("lod", "0.5,0.75").is_err());
        let r = o.resolve(&ProcessOptions::default()).unwrap();
        assert_eq!(r.mode, Mode::Global);
        assert!(!r.mips);
        assert_eq!(r.bc1_level, Level::Fast);
        assert_eq!(
            (r.format, r.container, r.zstd),
            (Format::Bc7, Container::Ktx2, 19)
        );
        assert_eq!(r.seam_weight, 12.5);
        assert_eq!(r.lod.as_slice(), [0.5, 0.25]);
        let mut bad = OptionPatch::default();
        bad.set_from_query("seam_weight", "-1").unwrap();
        assert!(bad.resolve(&ProcessOptions::default()).is_err());
    }

    #[test]
    fn json_nulls_and_unknown_names_are_refused() {
        assert!(OptionPatch::from_json(br#"{"bc1_level": null}"#).is_err());
        assert!(OptionPatch::from_json(br#"{"alpha": null}"#).is_err());
        assert!(OptionPatch::from_json(br#"{"colour": 1}"#).is_err());
        assert!(OptionPatch::from_json(br#"{"mips": "often"}"#).is_err());
        assert!(OptionPatch::from_json(b"[1]").is_err());
        let p = OptionPatch::from_json(br#"{"mips": false}"#).unwrap();
        assert!(!p.resolve(&ProcessOptions::default()).unwrap().mips);
    }

    #[test]
    fn json_part_overrides_query() {
        let mut q = OptionPatch::default();
        q.set_from_query("mode", "global").unwrap();
        q.set_from_query("dx10", "true").unwrap();
        let part = OptionPatch::from_json(br#"{"mode":"local"}"#).unwrap();
        let m = q
            .overridden_by(part)
            .resolve(&ProcessOptions::default())
            .unwrap();
        assert_eq!(m.mode, Mode::Local);
        assert!(m.dx10);
    }

    #[test]
    fn stored_options_keep_their_meaning() {
        let before: ProcessOptions = serde_json::from_str(
            r#"{"mode":"local","method":"erase","format":"dds","bc1_level":"default",
                "seam_aware":true,"seam_weight":48.0,"mips":false,"dx10":false}"#,
        )
        .unwrap();
        assert_eq!(before.resize, Resize::None);
        assert_eq!(before.alpha, AlphaOption::Drop);
        assert!(before.pictures);
        let d = ProcessOptions::default();
        let round: ProcessOptions = serde_json::from_value(Value::Object(d.to_json())).unwrap();
        assert_eq!(round, d);
        let whole = OptionPatch::from(&d).resolve(&ProcessOptions::service_default());
        assert_eq!(whole.unwrap(), d);
        // A new job gets a mip chain from the service as from `process`.
        assert!(d.mips && ProcessOptions::service_default().mips);
    }
}
