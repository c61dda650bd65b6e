//! The view page in a real browser: a server runs a job with
//! `keep_regular`, headless Chromium opens `GET /v1/jobs/{id}/view` with the
//! job's token, the page flies to a closed seam at a magnification where
//! bilinear filtering shows and screenshots each version; the colour step
//! across the seam line is measured on those screenshots. On Fox, the
//! worst closed seam, painted apart; on an atlas with a black gutter, a
//! seam whose step filtering makes, opened while its job still runs. Also
//! `seamstress view` over a folder `process --mips` wrote for CesiumMan
//! serves the same page, which shows the model textured.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::fd::FromRawFd;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine;
use serde_json::{json, Value};

mod common;
use common::server::Server;
use needs::needs;

const TOKEN: &str = "viewer:view-test-token-0123456789";
/// The page's canvas in the probe.
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;
/// Pixels either side of the seam line compared: a quarter of a texel at
/// the page's 16 pixels per texel, well inside each side's triangles.
const OFFSET: f64 = 4.0;

fn artefacts() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/view-test");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Headless Chromium driven over the DevTools protocol on a pipe (fds 3
/// and 4): no virtual time, so the page's own timings are real, and the
/// page's result is awaited rather than polled from a DOM dump. Killed with
/// its helpers on drop.
struct Browser {
    child: Child,
    to: File,
    from: BufReader<File>,
    next_id: u64,
}

impl Browser {
    fn start(profile: &Path, log: &Path) -> Browser {
        let mut to_child = [0; 2];
        let mut from_child = [0; 2];
        // SAFETY: plain pipe creation; the fds are owned below.
        unsafe {
            assert_eq!(libc::pipe2(to_child.as_mut_ptr(), libc::O_CLOEXEC), 0);
            assert_eq!(libc::pipe2(from_child.as_mut_ptr(), libc::O_CLOEXEC), 0);
        }
        let (child_reads, child_writes) = (to_child[0], from_child[1]);
        let mut cmd = Command::new("chromium");
        cmd.args([
            "--headless=new",
            // Chromium's sandbox does not start as root, which CI runs as.
            "--no-sandbox",
            "--disable-dev-shm-usage",
            "--disable-gpu",
            "--disable-background-networking",
            // WebGL on the CPU, with WEBGL_compressed_texture_s3tc.
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--remote-debugging-pipe",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("about:blank")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(File::create(log).unwrap())
        .process_group(0);
        // SAFETY: only async-signal-safe calls between fork and exec. The
        // pipe ends go first above every fd in use, so that placing them on
        // 3 and 4 cannot clobber one with the other; dup clears CLOEXEC.
        unsafe {
            cmd.pre_exec(move || {
                let r = libc::fcntl(child_reads, libc::F_DUPFD, 100);
                let w = libc::fcntl(child_writes, libc::F_DUPFD, 100);
                if r < 0 || w < 0 || libc::dup2(r, 3) < 0 || libc::dup2(w, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd.spawn().expect("chromium starts");
        // SAFETY: the parent's ends, owned from here; the child's are closed.
        let (to, from) = unsafe {
            libc::close(child_reads);
            libc::close(child_writes);
            (
                File::from_raw_fd(to_child[1]),
                File::from_raw_fd(from_child[0]),
            )
        };
        Browser {
            child,
            to,
            from: BufReader::new(from),
            next_id: 0,
        }
    }

    /// Sends a command and returns its answer, skipping events.
    fn call(&mut self, method: &str, params: Value, session: Option<&str>) -> Value {
        self.next_id += 1;
        let mut msg = json!({ "id": self.next_id, "method": method, "params": params });
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to.write_all(&bytes).expect("chromium reads its pipe");
        loop {
            let mut buf = Vec::new();
            self.from.read_until(0, &mut buf).unwrap();
            assert!(!buf.is_empty(), "chromium closed its pipe during {method}");
            buf.pop();
            let answer: Value = serde_json::from_slice(&buf).unwrap();
            if answer["id"] == json!(self.next_id) {
                return answer;
            }
        }
    }

    /// Opens `url` in a new tab and returns its session.
    fn open(&mut self, url: &str) -> String {
        let target = self.call("Target.createTarget", json!({ "url": url }), None);
        let target = target["result"]["targetId"].as_str().unwrap().to_string();
        let attached = self.call(
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
            None,
        );
        attached["result"]["sessionId"]
            .as_str()
            .unwrap()
            .to_string()
    }

    /// What `expression`, a promise of a string, resolves to in the tab.
    fn eval(&mut self, session: &str, expression: &str) -> String {
        // The first document is about:blank, replaced by the page: its
        // context is destroyed under an early evaluation, which is retried.
        for _ in 0..100 {
            let answer = self.call(
                "Runtime.evaluate",
                json!({ "expression": expression, "awaitPromise": true, "returnByValue": true }),
                Some(session),
            );
            if let Some(text) = answer["result"]["result"]["value"].as_str() {
                return text.to_string();
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!("the page never answered {expression}");
    }

    /// Opens `url` and returns what the page's `seamstressResult` resolves to.
    fn page_result(&mut self, url: &str) -> Value {
        let session = self.open(url);
        let wait = "new Promise(r => { const t = () => window.seamstressResult \
                    ? r(window.seamstressResult) : setTimeout(t, 50); t(); })";
        serde_json::from_str(&self.eval(&session, wait)).unwrap()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // SAFETY: signals only the process group started above.
        unsafe { libc::kill(-(self.child.id() as i32), libc::SIGKILL) };
        let _ = self.child.wait();
    }
}

/// Kills the browser's process group if the test outlives `limit`: a hung
/// page then fails the test instead of holding CI.
fn watchdog(browser: &Browser, limit: Duration) {
    let pid = browser.child.id() as i32;
    std::thread::spawn(move || {
        std::thread::sleep(limit);
        // SAFETY: signals only that process group; harmless if it is gone.
        unsafe { libc::kill(-pid, libc::SIGKILL) };
    });
}

fn http() -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder()
        .timeout(Duration::from_secs(120))
        .build()
        .unwrap()
}

fn bearer() -> &'static str {
    TOKEN.split_once(':').unwrap().1
}

/// Submits a shared model with `keep_regular` (no mips: the page looks at
/// level 0); with `wait`, waits for it to succeed. Returns the job.
fn submit(server: &Server, model: &str, content_type: &str, wait: bool) -> Value {
    let bytes = std::fs::read(common::shared_assets().join(model)).unwrap();
    let name = Path::new(model).file_name().unwrap().to_str().unwrap();
    let mut req = http()
        .post(server.url(&format!(
            "/v1/jobs?name={name}&keep_regular=true&mips=false"
        )))
        .bearer_auth(bearer())
        .header("content-type", content_type)
        .body(bytes);
    if wait {
        req = req.header("prefer", "wait=120");
    }
    let job: Value = req.send().unwrap().json().unwrap();
    if wait {
        assert_eq!(job["state"], "succeeded", "{job}");
    }
    job
}

/// The job with its report.
fn job(server: &Server, id: &str) -> Value {
    http()
        .get(server.url(&format!("/v1/jobs/{id}")))
        .bearer_auth(bearer())
        .send()
        .unwrap()
        .json()
        .unwrap()
}

/// The seam edges of the job's first texture, as the page reads them
/// (`<name>.edges.json`), in the file's order: the page's `#seam=N`.
fn edges(server: &Server, job: &Value) -> Vec<Value> {
    let name = job["report"]["textures"][0]["files"]["edges"]
        .as_str()
        .unwrap_or_else(|| panic!("no edges.json: {job}"));
    let file: Value = http()
        .get(server.url(&format!(
            "/v1/jobs/{}/files/{name}",
            job["id"].as_str().unwrap()
        )))
        .bearer_auth(bearer())
        .send()
        .unwrap()
        .json()
        .unwrap();
    file["edges"].as_array().unwrap().clone()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

/// The closed seam whose step in the input comes from filtering rather
/// than from the paint, if the texture has one: an edge's `jump` is the
/// difference between the colours its two charts paint along it, each
/// side sampled with the taps outside its own chart dropped (what
/// discarding taps shows), and `residual[0]` the step that plain bilinear
/// sampling of the input shows. Where the jump is under a quarter of that
/// step, at least three quarters of the step is taps reaching across the
/// chart's border into the gutter or another chart: "a seam where
/// filtering, not painting, causes the step". Of those at least 8 texels
/// long (so that the seam crosses the close-up), the one with the largest
/// input step. `width` and `height` are the texture's, in texels.
fn filtering_seam(edges: &[Value], width: f64, height: f64) -> Option<usize> {
    let texels = |h: &Value| {
        let c = |i: usize, j: usize| f(&h[i][j]);
        ((c(1, 0) - c(0, 0)) * width).hypot((c(1, 1) - c(0, 1)) * height)
    };
    edges
        .iter()
        .enumerate()
        .filter(|(_, e)| {
            e["closed"] == true
                && f(&e["jump"]) < 0.25 * f(&e["residual"][0])
                && texels(&e["a"]).min(texels(&e["b"])) >= 8.0
        })
        .max_by(|(_, x), (_, y)| f(&x["residual"][0]).total_cmp(&f(&y["residual"][0])))
        .map(|(k, _)| k)
}

/// The largest share of a closed seam's input step that filtering makes
/// (1 − jump / input step), and that seam's index.
fn largest_filtering_share(edges: &[Value]) -> (f64, usize) {
    edges
        .iter()
        .enumerate()
        .filter(|(_, e)| e["closed"] == true && f(&e["residual"][0]) > 0.0)
        .map(|(k, e)| (1.0 - f(&e["jump"]) / f(&e["residual"][0]), k))
        .max_by(|x, y| x.0.total_cmp(&y.0))
        .unwrap()
}

/// Mean RMS (over RGB, in 8-bit levels) between pixels `OFFSET` either side
/// of the seam line, over the line's points well inside the picture.
fn step_across(png: &image::RgbImage, line: &[[f64; 2]]) -> (f64, usize) {
    let (w, h) = (f64::from(png.width()), f64::from(png.height()));
    let (mut sum, mut n) = (0.0, 0);
    for pair in line.windows(2) {
        let (p, q) = (pair[0], pair[1]);
        let d = [q[0] - p[0], q[1] - p[1]];
        let len = d[0].hypot(d[1]);
        if len == 0.0 {
            continue;
        }
        let normal = [-d[1] / len, d[0] / len];
        let at = |s: f64| [p[0] + s * normal[0], p[1] + s * normal[1]];
        let (a, b) = (at(-OFFSET), at(OFFSET));
        let inside = |c: [f64; 2]| c[0] >= 8.0 && c[1] >= 8.0 && c[0] < w - 8.0 && c[1] < h - 8.0;
        if !inside(a) || !inside(b) {
            continue;
        }
        let px = |c: [f64; 2]| png.get_pixel(c[0] as u32, c[1] as u32).0;
        let (pa, pb) = (px(a), px(b));
        let sq: f64 = (0..3)
            .map(|c| (f64::from(pa[c]) - f64::from(pb[c])).powi(2))
            .sum();
        sum += (sq / 3.0).sqrt();
        n += 1;
    }
    (if n > 0 { sum / n as f64 } else { f64::NAN }, n)
}

/// Opens the page with `#probe` and `extra`, saves its screenshot of each
/// version as `{tag}-{mode}.png` and returns the page's result with the
/// screenshots; `token` for a server that asks for one.
fn shots(
    browser: &mut Browser,
    url: &str,
    token: Option<&str>,
    tag: &str,
    extra: &str,
) -> (Value, Vec<(String, image::RgbImage)>) {
    let token = token.map_or(String::new(), |t| format!("token={t}&"));
    let r = browser.page_result(&format!(
        "{url}#{token}width={WIDTH}&height={HEIGHT}{extra}"
    ));
    assert_eq!(r["ok"], true, "the page failed: {r}");
    assert_eq!(r["errors"], json!([]), "errors on the page: {r}");
    let mut out = Vec::new();
    for (mode, shot) in r["shots"].as_object().expect("screenshots") {
        let data = shot["png"].as_str().unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(data.trim_start_matches("data:image/png;base64,"))
            .unwrap();
        std::fs::write(artefacts().join(format!("{tag}-{mode}.png")), &bytes).unwrap();
        let png = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert_eq!(png.dimensions(), (WIDTH, HEIGHT));
        out.push((mode.clone(), png));
    }
    (r, out)
}

/// The page's screenshots of each version at one seam (`which`: `probe=K`
/// for stop K of "next seam", or `probe&seam=N` for edge N), and the step
/// across the seam on each.
fn probe(browser: &mut Browser, url: &str, tag: &str, which: &str) -> (Value, Vec<(String, f64)>) {
    let (r, pictures) = shots(browser, url, Some(bearer()), tag, &format!("&{which}"));
    let mut steps = Vec::new();
    for (mode, png) in &pictures {
        let line: Vec<[f64; 2]> = serde_json::from_value(r["shots"][mode]["line"].clone()).unwrap();
        let (step, n) = step_across(png, &line);
        assert!(n >= 10, "{mode}: the seam crosses only {n} sampled points");
        steps.push((mode.clone(), step));
    }
    (r, steps)
}

fn step(steps: &[(String, f64)], mode: &str) -> f64 {
    steps
        .iter()
        .find(|(m, _)| m == mode)
        .unwrap_or_else(|| panic!("no {mode} screenshot: {steps:?}"))
        .1
}

/// A band across the seam from each version's screenshot `{tag}-{mode}.png`,
/// side by side (input, regular BC1, seam-aware BC1, taps discarded): the
/// README's pictures, `docs/view-*-seam.png`.
fn strip(tag: &str) -> image::RgbImage {
    let mut strip = image::RgbImage::new(WIDTH, HEIGHT);
    let band = WIDTH / 4;
    for (k, mode) in ["input", "regular", "seam_aware", "discard"]
        .iter()
        .enumerate()
    {
        let shot = image::open(artefacts().join(format!("{tag}-{mode}.png")))
            .unwrap()
            .to_rgb8();
        let view = image::imageops::crop_imm(&shot, (WIDTH - band) / 2, 0, band, HEIGHT);
        image::imageops::replace(&mut strip, &view.to_image(), i64::from(band) * k as i64, 0);
    }
    strip
}

/// Probes the seam [`filtering_seam`] picks and checks the order on
/// it: the step largest with the input, smaller with regular BC1, smaller
/// still with seam-aware BC1, and small with the taps discarded too.
fn check_filtering_seam(
    browser: &mut Browser,
    page: &str,
    tag: &str,
    edges: &[Value],
    k: usize,
) -> Vec<(String, f64)> {
    let (r, steps) = probe(browser, page, tag, &format!("probe&seam={k}"));
    assert_eq!(r["index"], json!(k), "the page flew to another seam: {r}");
    let e = &edges[k];
    eprintln!(
        "{tag}: seam {k} (jump {}, input residual {}): steps {steps:?}",
        e["jump"], e["residual"][0]
    );
    let (input, regular, aware, discard) = (
        step(&steps, "input"),
        step(&steps, "regular"),
        step(&steps, "seam_aware"),
        step(&steps, "discard"),
    );
    assert!(
        input > 10.0 * regular,
        "input {input:.2}, regular BC1 {regular:.2}"
    );
    assert!(
        regular > aware,
        "regular {regular:.2}, seam-aware {aware:.2}"
    );
    // Small: under 2 levels, where a step stops showing on most content,
    // and a tenth of the input's at most.
    assert!(
        discard < 2.0 && discard < 0.1 * input,
        "taps discarded {discard:.2}, input {input:.2}"
    );
    steps
}

/// Fox (2048²), as the issue names it: its worst closed seam, whose sides
/// are painted apart, in every version, by the GPU's decoder and by the
/// page's.
#[needs(chromium)]
#[test]
fn the_view_page_shows_the_seams_closing() {
    if !common::CHROMIUM.available() {
        return;
    }
    let started = Instant::now();
    let scratch = tempdir("job");
    let server = Server::start(&scratch.join("data"), &["--token", TOKEN]);
    let fox = submit(&server, "Fox/Fox.gltf", "model/gltf+json", true);
    let id = fox["id"].as_str().unwrap().to_string();
    let job_s = started.elapsed().as_secs_f64();

    // Without the token the job is not there for the page either.
    let page = server.url(&format!("/v1/jobs/{id}/view"));
    let html = http().get(&page).send().unwrap();
    assert_eq!(html.status(), 200);
    assert!(html.text().unwrap().contains("view.js"));
    let anonymous = http()
        .get(server.url(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap();
    assert_eq!(anonymous.status(), 401);

    let mut browser = Browser::start(&scratch.join("profile"), &artefacts().join("chromium.log"));
    watchdog(&browser, Duration::from_secs(120));
    let opened = Instant::now();
    let (r, worst) = probe(&mut browser, &page, "fox-gpu", "probe=0");
    let page_s = opened.elapsed().as_secs_f64();
    // The page's own decoder, for browsers without S3TC.
    let (by_page, decoded) = probe(
        &mut browser,
        &page,
        "fox-page-decoder",
        "probe=0&decode=page",
    );
    eprintln!(
        "job {job_s:.1} s; Fox 2048²: page loaded and rendered in {:.0} ms (page's clock), \
         {page_s:.1} s with the probe; S3TC in WebGL: {}",
        f(&r["load_ms"]),
        r["s3tc"]
    );
    eprintln!("worst closed seam {}: steps {worst:?}", r["edge"]);
    strip("fox-gpu")
        .save(artefacts().join("view-fox-seam.png"))
        .unwrap();

    assert_eq!(
        r["s3tc"], true,
        "SwiftShader offers S3TC: the GPU path is tested"
    );
    let (input, erased, regular, aware, discard) = (
        step(&worst, "input"),
        step(&worst, "erased"),
        step(&worst, "regular"),
        step(&worst, "seam_aware"),
        step(&worst, "discard"),
    );
    assert!(
        input > 10.0 * regular,
        "input {input:.2}, regular BC1 {regular:.2}"
    );
    assert!(
        regular > aware,
        "regular {regular:.2}, seam-aware {aware:.2}"
    );
    assert!(
        aware < 1.5 && erased < 1.5,
        "seam-aware {aware:.2}, erased {erased:.2}"
    );
    // Discarding taps shows each side's own chart: it removes bilinear
    // bleeding, never the paint. On this seam the sides are painted apart
    // by its jump, so the step stays near it, and never above the input's.
    let jump = f(&r["edge"]["jump"]);
    assert!(
        discard <= input + 1.0,
        "discard {discard:.2}, input {input:.2}"
    );
    assert!(
        (discard - jump).abs() < 0.3 * jump,
        "discard {discard:.2}, jump {jump:.2}"
    );
    // The ideal palette in the page and the GPU's decoder differ by a
    // rounding at most: the steps agree.
    assert_eq!(by_page["s3tc"], false);
    for mode in ["regular", "seam_aware"] {
        let (gpu, page) = (step(&worst, mode), step(&decoded, mode));
        assert!(
            (gpu - page).abs() < 0.5,
            "{mode}: GPU {gpu:.2}, page {page:.2}"
        );
    }
    eprintln!("decoded in the page: steps {decoded:?}");

    // Fox's painter carried each chart's colours past its border, so taps
    // that cross a seam read nearly what the chart paints: on Fox the steps
    // are in the paint, and discarding taps leaves them (the gutter test
    // below has the seams where it does not).
    let edges = edges(&server, &job(&server, &id));
    match filtering_seam(&edges, 2048.0, 2048.0) {
        Some(k) => {
            check_filtering_seam(&mut browser, &page, "fox-filtering", &edges, k);
        }
        None => {
            let (share, k) = largest_filtering_share(&edges);
            eprintln!(
                "Fox has no closed seam whose step filtering makes (three quarters of it or \
                 more): the largest share is {:.0}%, on seam {k} (jump {}, input residual {})",
                share * 100.0,
                edges[k]["jump"],
                edges[k]["residual"][0]
            );
        }
    }
    eprintln!("test {:.1} s", started.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&scratch);
}

/// blub re-cut into an atlas with a black gutter (2048², 1019 seams, every
/// seam's sides painted alike): bilinear taps that cross a chart's border
/// read black, the step that discarding taps removes as erasure does. The
/// job is opened while it runs, in the job list and in its own page, which
/// show its progress and then its model.
#[needs(chromium)]
#[test]
fn discarding_taps_closes_the_seams_a_gutter_opens() {
    if !common::CHROMIUM.available() {
        return;
    }
    let started = Instant::now();
    let scratch = tempdir("gutter");
    let server = Server::start(&scratch.join("data"), &["--token", TOKEN]);
    let mut browser = Browser::start(
        &scratch.join("profile"),
        &artefacts().join("chromium-gutter.log"),
    );
    watchdog(&browser, Duration::from_secs(180));
    let submitted = submit(
        &server,
        "blub_atlas/blub_atlas_black.glb",
        "model/gltf-binary",
        false,
    );
    let id = submitted["id"].as_str().unwrap().to_string();
    let running = |state: &Value| state == "queued" || state == "running";
    assert!(running(&submitted["state"]), "{submitted}");

    let list = browser.open(&format!("{}#token={}", server.url("/v1/view"), bearer()));
    let page = server.url(&format!("/v1/jobs/{id}/view"));
    let r = browser.page_result(&format!("{page}#token={}", bearer()));
    assert_eq!(r["ok"], true, "the page failed: {r}");
    let seen = r["seen"].as_array().unwrap();
    assert!(
        running(&seen[0]) && seen.last() == Some(&json!("succeeded")),
        "the page opened on the running job should wait for it: {r}"
    );
    eprintln!(
        "blub_atlas_black 2048², 1019 seams: the page waited {:.1} s for the job, then loaded \
         and rendered in {:.0} ms",
        f(&r["waited_ms"]) / 1000.0,
        f(&r["load_ms"])
    );
    // The list shows the job running, then finished with a link to its page.
    let wait_listed = format!(
        "new Promise(r => {{ const t = () => {{ const s = (window.seamstressShown || {{}})['{id}'] \
         || []; s.includes('succeeded') && document.querySelector('a[href=\"/v1/jobs/{id}/view\"]') \
         ? r(JSON.stringify(s)) : setTimeout(t, 100); }}; t(); }})"
    );
    let listed: Vec<Value> = serde_json::from_str(&browser.eval(&list, &wait_listed)).unwrap();
    assert!(
        running(&listed[0]) && listed.last() == Some(&json!("succeeded")),
        "the list should have refreshed from running to succeeded: {listed:?}"
    );

    let job = job(&server, &id);
    let edges = edges(&server, &job);
    let k = filtering_seam(&edges, 2048.0, 2048.0)
        .expect("a black gutter makes steps that filtering causes");
    check_filtering_seam(&mut browser, &page, "gutter", &edges, k);
    strip("gutter")
        .save(artefacts().join("view-gutter-seam.png"))
        .unwrap();
    eprintln!("test {:.1} s", started.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&scratch);
}

fn tempdir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-view-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Whether a screenshot's pixel shows the model, not the page's clear
/// colour.
fn on_model(p: &image::Rgb<u8>) -> bool {
    const CLEAR: [i32; 3] = [0x20, 0x20, 0x28];
    (0..3).any(|c| (i32::from(p.0[c]) - CLEAR[c]).abs() > 4)
}

/// `seamstress view` over what `process --mips` wrote for CesiumMan (a
/// skinned model, a JPEG texture, a mip chain): it prints the page's URL
/// and serves the folder as the service serves a job (the page, the job
/// with the folder's report, and only the folder's files), and in a
/// browser the page shows the model textured in every version.
#[test]
fn seamstress_view_serves_a_process_folder() {
    let dir = tempdir("cli");
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .arg(common::shared_assets().join("CesiumMan/CesiumMan.gltf"))
        .args(["--mips", "--pictures", "--keep-regular", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("view")
        .arg(&out)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line.trim().to_string();
    let check = || {
        assert!(
            url.starts_with("http://127.0.0.1:") && url.ends_with("/view"),
            "{url}"
        );
        let client = http();
        let page = client.get(&url).send().unwrap().text().unwrap();
        assert!(page.contains("/v1/view/assets/view.js"), "{page}");
        let base = url.trim_end_matches("/view");
        let job: Value = client.get(base).send().unwrap().json().unwrap();
        assert_eq!(job["state"], "succeeded");
        let files = &job["report"]["textures"][0]["files"];
        for key in ["dds", "regular", "input", "charts", "edges", "erased"] {
            let name = files[key]
                .as_str()
                .unwrap_or_else(|| panic!("no {key}: {files}"));
            let mut body = Vec::new();
            let resp = client.get(format!("{base}/files/{name}")).send().unwrap();
            assert_eq!(resp.status(), 200, "{name}");
            resp.take(u64::MAX).read_to_end(&mut body).unwrap();
            assert_eq!(body, std::fs::read(out.join(name)).unwrap(), "{name}");
        }
        let dds = std::fs::read(out.join(files["dds"].as_str().unwrap())).unwrap();
        let mip_count = u32::from_le_bytes(dds[28..32].try_into().unwrap());
        assert!(mip_count > 1, "process --mips wrote {mip_count} level");
        let outside = client
            .get(format!("{base}/files/..%2Freport.json"))
            .send()
            .unwrap();
        assert_eq!(outside.status(), 404);
        let three = client
            .get(url.replace(
                "/v1/jobs/local/view",
                "/v1/view/assets/three/build/three.module.js",
            ))
            .send()
            .unwrap();
        assert_eq!(three.status(), 200);
        if common::CHROMIUM.available() {
            renders_textured(&dir, &url);
        }
    };
    let outcome = std::panic::catch_unwind(check);
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&dir);
    if let Err(e) = outcome {
        std::panic::resume_unwind(e);
    }
}

/// The page from `seamstress view` on the whole of CesiumMan: every version
/// shows the model textured (many colours, not black), and the shipped DDS,
/// sampled through its mip chain at this distance, shows the input's colours.
fn renders_textured(dir: &Path, url: &str) {
    let mut browser = Browser::start(&dir.join("profile"), &artefacts().join("chromium-cli.log"));
    watchdog(&browser, Duration::from_secs(90));
    let (r, pictures) = shots(&mut browser, url, None, "cesium-man", "&probe=overview");
    assert_eq!(r["s3tc"], true, "{r}");
    let input = &pictures.iter().find(|(m, _)| m == "input").unwrap().1;
    let mut summary = Vec::new();
    for (mode, png) in &pictures {
        let model: Vec<(&image::Rgb<u8>, &image::Rgb<u8>)> = png
            .pixels()
            .zip(input.pixels())
            .filter(|(p, q)| on_model(p) || on_model(q))
            .collect();
        let n = model.len().max(1) as f64;
        let share = n / f64::from(WIDTH * HEIGHT);
        let level = |p: &image::Rgb<u8>| p.0.iter().map(|&c| f64::from(c)).sum::<f64>() / 3.0;
        let mean = model.iter().map(|(p, _)| level(p)).sum::<f64>() / n;
        let colours = model
            .iter()
            .map(|(p, _)| p.0.map(|c| c >> 3))
            .collect::<std::collections::HashSet<_>>()
            .len();
        // Mean absolute difference from the input's screenshot, over the
        // model.
        let differs = model
            .iter()
            .map(|(p, q)| {
                (0..3)
                    .map(|c| (f64::from(p.0[c]) - f64::from(q.0[c])).abs())
                    .sum::<f64>()
                    / 3.0
            })
            .sum::<f64>()
            / n;
        summary.push(format!(
            "{mode}: {:.1}% of the picture, mean {mean:.0}, {colours} colours, {differs:.2} levels \
             from the input",
            share * 100.0
        ));
        assert!(
            share > 0.03,
            "{mode}: the model covers {share:.3} of the picture"
        );
        assert!(mean > 40.0, "{mode}: the model is dark (mean {mean:.1})");
        assert!(
            colours > 100,
            "{mode}: only {colours} colours: not textured"
        );
        assert!(differs < 8.0, "{mode}: {differs:.2} levels from the input");
    }
    eprintln!("CesiumMan from `seamstress view`: {summary:?}");
}
