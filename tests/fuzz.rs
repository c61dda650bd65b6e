//! Mutated models through the `seamstress` binary under a 4 GiB address-space
//! limit: none may abort (signal, panic, out of memory) or run past 30 s.
//! Every case must end in exit status 0 (processed) or 2 (bad input, one
//! line naming the file).
//!
//! A bounded run is part of the test suite (`SEAMSTRESS_FUZZ_CASES`, 240 by
//! default); the long campaign is the same test with a larger count:
//!
//! ```text
//! SEAMSTRESS_FUZZ_CASES=100000 cargo test --release --test fuzz -- --nocapture
//! ```
//!
//! Cases are numbered; case `n` is the same mutation on any machine, so a
//! failure reported as "case 8123" is replayed with
//! `SEAMSTRESS_FUZZ_FIRST=8123 SEAMSTRESS_FUZZ_CASES=1`. Failing inputs are
//! kept in the folder the test prints.

use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

mod common;

const SEEDS: [&str; 3] = [
    "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
    "cube/cube_gradient_128.glb",
    "cube/cube_bad_background_100.glb",
];
const ADDRESS_SPACE: u64 = 4 << 30;
const TIME_LIMIT: Duration = Duration::from_secs(30);

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// splitmix64: a fixed sequence per case.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A GLB's JSON and binary chunks.
struct Glb {
    json: Vec<u8>,
    bin: Vec<u8>,
}

impl Glb {
    fn parse(b: &[u8]) -> Glb {
        let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize;
        let json_len = u32_at(12);
        let json = b[20..20 + json_len].to_vec();
        let bin_at = 20 + json_len;
        let bin = if bin_at + 8 <= b.len() {
            let n = u32_at(bin_at);
            b[bin_at + 8..bin_at + 8 + n].to_vec()
        } else {
            Vec::new()
        };
        Glb { json, bin }
    }

    fn bytes(&self) -> Vec<u8> {
        let mut json = self.json.clone();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        let mut bin = self.bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
        let mut out = Vec::with_capacity(total);
        out.extend(b"glTF");
        out.extend(2u32.to_le_bytes());
        out.extend((total as u32).to_le_bytes());
        out.extend((json.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(&json);
        if !bin.is_empty() {
            out.extend((bin.len() as u32).to_le_bytes());
            out.extend(b"BIN\0");
            out.extend(&bin);
        }
        out
    }
}

const FLOATS: [f32; 9] = [
    1e6,
    -1e6,
    1e4,
    f32::NAN,
    f32::INFINITY,
    1e-30,
    0.0,
    65536.0,
    -0.5,
];
const INTS: [u32; 7] = [0, 1, 0xFFFF_FFFF, 0x7FFF_FFFF, 65535, 1 << 20, 3];

/// One mutation of `seed`, chosen by `rng`.
fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut glb = Glb::parse(seed);
    let rounds = 1 + rng.below(3);
    for _ in 0..rounds {
        match rng.below(7) {
            // Bit flips anywhere in the binary chunk (indices, UVs, images).
            0 if !glb.bin.is_empty() => {
                for _ in 0..1 + rng.below(8) {
                    let at = rng.below(glb.bin.len());
                    glb.bin[at] ^= 1 << rng.below(8);
                }
            }
            // An extreme float or integer at an aligned place.
            1 if glb.bin.len() >= 4 => {
                let at = rng.below(glb.bin.len() / 4) * 4;
                let v = if rng.below(2) == 0 {
                    FLOATS[rng.below(FLOATS.len())].to_le_bytes()
                } else {
                    INTS[rng.below(INTS.len())].to_le_bytes()
                };
                glb.bin[at..at + 4].copy_from_slice(&v);
            }
            // A number in the JSON replaced by an extreme one.
            2 => {
                let digits: Vec<usize> = (0..glb.json.len())
                    .filter(|&i| glb.json[i].is_ascii_digit())
                    .collect();
                if let Some(&at) = digits.get(rng.below(digits.len())) {
                    let end = (at..glb.json.len())
                        .find(|&i| !glb.json[i].is_ascii_digit())
                        .unwrap_or(glb.json.len());
                    let new = [
                        "0",
                        "1",
                        "4294967295",
                        "99999999999",
                        "65536",
                        "7",
                        "-1",
                        "1e300",
                    ][rng.below(8)];
                    glb.json.splice(at..end, new.bytes());
                }
            }
            // A texture transform that tiles the texture a great many times.
            3 => {
                let text = String::from_utf8_lossy(&glb.json).into_owned();
                let scale = [1e4, 1e2, 1e6, -3.0, 0.0][rng.below(5)];
                let with = text.replacen(
                    "\"baseColorTexture\":{",
                    &format!(
                        "\"baseColorTexture\":{{\"extensions\":{{\"KHR_texture_transform\":{{\"scale\":[{scale},{scale}],\"offset\":[0.5,-7]}}}},"
                    ),
                    1,
                );
                glb.json = with.into_bytes();
            }
            // The PNG header announcing another size (CRC fixed).
            4 => {
                if let Some(at) = find(&glb.bin, b"IHDR") {
                    if at + 17 + 4 <= glb.bin.len() {
                        let side = [0u32, 1, 3, 8192, 16384, 65535, 1 << 30][rng.below(7)];
                        let other = [1u32, 4, 211, 16384][rng.below(4)];
                        glb.bin[at + 4..at + 8].copy_from_slice(&side.to_be_bytes());
                        glb.bin[at + 8..at + 12].copy_from_slice(&other.to_be_bytes());
                        let crc = common::crc32(&glb.bin[at..at + 17]);
                        glb.bin[at + 17..at + 21].copy_from_slice(&crc.to_be_bytes());
                    }
                }
            }
            // Truncation.
            5 => {
                let keep = rng.below(glb.bin.len() + 1);
                glb.bin.truncate(keep);
            }
            // A byte of the JSON changed.
            _ if !glb.json.is_empty() => {
                let at = rng.below(glb.json.len());
                glb.json[at] = b"{}[],:\"0e-.x "[rng.below(13)];
            }
            _ => {}
        }
    }
    glb.bytes()
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// How a case ended.
enum Outcome {
    Done,
    Refused,
    Failed(String),
}

fn run_case(input: &Path, out: &Path) -> Outcome {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    cmd.args(["process", "--bc1-level", "fast", "--out"])
        .arg(out)
        .arg(input)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    common::limit_address_space(&mut cmd, ADDRESS_SPACE);
    let mut child = cmd.spawn().expect("seamstress starts");
    let started = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if started.elapsed() > TIME_LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            return Outcome::Failed(format!("ran past {TIME_LIMIT:?}"));
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let mut err = String::new();
    use std::io::Read;
    let _ = child.stderr.take().unwrap().read_to_string(&mut err);
    match (status.code(), status.signal()) {
        (Some(0), _) => Outcome::Done,
        (Some(2), _) if err.trim().lines().count() == 1 && err.contains(".glb") => Outcome::Refused,
        (Some(2), _) => Outcome::Failed(format!("exit 2 without one line naming the file: {err}")),
        (Some(c), _) => Outcome::Failed(format!("exit {c}: {err}")),
        (None, sig) => Outcome::Failed(format!("killed by signal {sig:?}: {err}")),
    }
}

#[test]
fn mutated_models_never_abort_or_hang() {
    let cases = env_u64("SEAMSTRESS_FUZZ_CASES", 240);
    let first = env_u64("SEAMSTRESS_FUZZ_FIRST", 0);
    let assets = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets");
    let seeds: Vec<Vec<u8>> = SEEDS
        .iter()
        .map(|s| std::fs::read(assets.join(s)).unwrap())
        .collect();
    let dir = std::env::temp_dir().join(format!("seamstress-fuzz-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("failures")).unwrap();

    let next = AtomicU64::new(first);
    let (done, refused) = (AtomicU64::new(0), AtomicU64::new(0));
    let failures = Mutex::new(Vec::new());
    let started = Instant::now();
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    std::thread::scope(|s| {
        for t in 0..threads {
            let (seeds, dir, next, done, refused, failures) =
                (&seeds, &dir, &next, &done, &refused, &failures);
            s.spawn(move || loop {
                let n = next.fetch_add(1, Ordering::Relaxed);
                if n >= first + cases {
                    break;
                }
                let mut rng = Rng(n);
                let seed = &seeds[rng.below(seeds.len())];
                let input = dir.join(format!("t{t}.glb"));
                std::fs::write(&input, mutate(seed, &mut rng)).unwrap();
                match run_case(&input, &dir.join(format!("out{t}"))) {
                    Outcome::Done => done.fetch_add(1, Ordering::Relaxed),
                    Outcome::Refused => refused.fetch_add(1, Ordering::Relaxed),
                    Outcome::Failed(why) => {
                        let keep = dir.join(format!("failures/case{n}.glb"));
                        let _ = std::fs::copy(&input, &keep);
                        failures.lock().unwrap().push(format!("case {n}: {why}"));
                        0
                    }
                };
                if (n - first + 1).is_multiple_of(5000) {
                    eprintln!("{} cases, {:?}", n - first + 1, started.elapsed());
                }
            });
        }
    });
    let failures = failures.into_inner().unwrap();
    eprintln!(
        "fuzz: {cases} cases from {first} in {:.0} s: {} processed, {} refused as bad input, {} failed; inputs in {}",
        started.elapsed().as_secs_f64(),
        done.load(Ordering::Relaxed),
        refused.load(Ordering::Relaxed),
        failures.len(),
        dir.display()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    let _ = std::fs::remove_dir_all(&dir);
}
