//! Screenshot of a running viewer, as the README shows it: opens the page in headless
//! Chromium, waits until samples and every camera's thumbnail have arrived (and a few seconds
//! of trails), saves a PNG.
//!
//! `cargo run -p handflow-e2e --example viewer_screenshot -- [URL] [OUT.png] [SECONDS]`
//! (defaults: http://127.0.0.1:8787/, viewer.png, 6).

use std::time::Duration;

use handflow_e2e::browser::{chromium_binary, Browser};

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let url = args.first().map_or("http://127.0.0.1:8787/", String::as_str);
    let out = args.get(1).map_or("viewer.png", String::as_str);
    let seconds: f64 = args.get(2).map_or(Ok(6.0), |s| s.parse()).map_err(|e| format!("SECONDS: {e}"))?;
    let chromium = chromium_binary().ok_or("no `chromium` on the path (apt-get install chromium)")?;
    let mut browser = Browser::start(&chromium, 1280, 800);
    browser.navigate(url);
    let state = "(() => { const v = window.handflowViewer; return v ? v.state() : null; })()";
    browser.wait_for(state, Duration::from_secs(120), |s| {
        let cameras = s["rigCameras"].as_u64().unwrap_or(0);
        s["samples"].as_u64() > Some(0)
            && cameras > 0
            && s["thumbnailCameras"].as_array().is_some_and(|t| t.len() as u64 >= cameras)
    });
    std::thread::sleep(Duration::from_secs_f64(seconds));
    std::fs::write(out, browser.screenshot()).map_err(|e| format!("writing `{out}`: {e}"))?;
    println!("{out}");
    Ok(())
}
