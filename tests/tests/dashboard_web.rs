//! The fleet web page in a real headless browser (Debian's `chromium`): after a run, the page's
//! fleet table shows the trolley with fruits, its plan view draws the trolley's row, camera and
//! one dot per fruit, its fruit table shows the fitted volumes, and a screenshot is saved as a CI
//! artifact.

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use glasshouse_dashboard::DashboardSettings;
use glasshouse_tests::{test_edge_config, within, Pipeline};

fn chromium() -> String {
    for name in ["chromium", "chromium-browser", "google-chrome"] {
        if Command::new(name)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
        {
            return name.to_owned();
        }
    }
    panic!("no headless browser: install Debian's chromium (apt-get install chromium)");
}

fn headless(browser: &str, args: &[&str]) -> std::process::Output {
    Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--hide-scrollbars",
            // Let the page's scripts fetch and render before the DOM or screenshot is taken.
            "--virtual-time-budget=4000",
        ])
        .args(args)
        .output()
        .expect("chromium runs")
}

/// Where CI artifacts go: target/artifacts/.
fn artifacts_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    let target = exe
        .ancestors()
        .nth(3)
        .expect("target dir above target/<profile>/deps")
        .to_path_buf();
    let dir = target.join("artifacts");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

/// The number in the fleet table's fruits cell of trolley `tid`, from the rendered DOM.
fn fruits_in_dom(dom: &str, tid: &str) -> Option<u64> {
    let row_start = dom.find(&format!("<tr data-trolley=\"{tid}\">"))?;
    let row = &dom[row_start..];
    let row = &row[..row.find("</tr>")?];
    let cell = row.find("<td class=\"fruits\">")? + "<td class=\"fruits\">".len();
    row[cell..].split('<').next()?.trim().parse().ok()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn fleet_page_shows_the_trolley_with_fruits_in_a_real_browser() {
    let browser = chromium();
    let settings = DashboardSettings {
        http_listen: Some("127.0.0.1:0".into()),
        ..DashboardSettings::default()
    };
    let mut pipeline = Pipeline::start_with(test_edge_config(5), settings).await;
    pipeline.run_to_end(180).await;
    let addr = within(10, "web page address", async {
        loop {
            if let Some(addr) = *pipeline.dashboard_counters.http_addr.lock().expect("addr") {
                return addr;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    let url = format!("http://{addr}/");

    // The JSON API first: the browser shows what it says.
    let api = headless(
        &browser,
        &["--dump-dom", &format!("http://{addr}/api/fleet")],
    );
    let api_text = String::from_utf8_lossy(&api.stdout);
    assert!(api_text.contains("\"id\":\"t1\""), "fleet API: {api_text}");

    let browser_task = {
        let (browser, url) = (browser.clone(), url.clone());
        tokio::task::spawn_blocking(move || headless(&browser, &["--dump-dom", &url]))
    };
    let dom = within(60, "chromium --dump-dom", browser_task)
        .await
        .expect("browser task");
    let dom = String::from_utf8_lossy(&dom.stdout).into_owned();
    let fruits = fruits_in_dom(&dom, "t1");
    assert!(
        fruits.is_some_and(|n| n > 0),
        "fleet table shows no fruits for t1 (got {fruits:?}); DOM:\n{dom}"
    );
    assert!(dom.contains("Fruits of t1"), "no fruit table for t1");
    // The plan view: t1's panel with its row, its camera and a dot per fruit of the table.
    let panel_start = dom
        .find("<svg width=")
        .and_then(|_| dom.find("data-trolley=\"t1\"><rect"))
        .unwrap_or_else(|| panic!("no plan panel for t1; DOM:\n{dom}"));
    let panel = &dom[panel_start..];
    let panel = &panel[..panel.find("</svg>").expect("panel end")];
    assert!(
        panel.contains("class=\"region\""),
        "no row in the plan: {panel}"
    );
    assert!(
        panel.contains("class=\"camera\""),
        "no camera in the plan: {panel}"
    );
    assert_eq!(
        panel.matches("class=\"fruit\"").count() as u64,
        fruits.unwrap_or(0),
        "a dot per fruit: {panel}"
    );
    // The fruit table shows the fitted volume of at least one fruit.
    let fitted = dom.matches("<td class=\"fitted\">").count();
    let unfitted = dom.matches("<td class=\"fitted\">–</td>").count();
    assert!(fitted > unfitted, "no fitted volume in the fruit table");

    let shot = artifacts_dir().join("dashboard-page.png");
    let shot_arg = format!("--screenshot={}", shot.display());
    let browser_task = {
        let (browser, url) = (browser.clone(), url.clone());
        tokio::task::spawn_blocking(move || {
            headless(&browser, &["--window-size=1280,900", &shot_arg, &url])
        })
    };
    within(60, "chromium --screenshot", browser_task)
        .await
        .expect("browser task");
    let png = std::fs::read(&shot).expect("screenshot written");
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "screenshot is {} bytes",
        png.len()
    );
    pipeline.stop().await;
}
