//! The fleet web page in a real headless browser (Debian's `chromium`): after a run, the page's
//! fleet table shows the trolley with fruits, its plan view draws the trolley's row, camera and
//! one dot per fruit, its fruit table shows the fitted volumes, its season table shows the
//! trolley's fruits of the season, its chart a line per fruit and its history table each fruit's
//! observed colour (a red swatch: the simulated fruit are red), the season CSV downloads with
//! its header and a colour per record, and a screenshot is saved as a CI artifact.

use std::io::{Read, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

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

/// The number in the cell of class `class` of trolley `tid`'s row in table `table`, from the
/// rendered DOM.
fn number_in_table(dom: &str, table: &str, tid: &str, class: &str) -> Option<u64> {
    let table_start = dom.find(&format!("<table id=\"{table}\">"))?;
    let table = &dom[table_start..];
    let table = &table[..table.find("</table>")?];
    let row_start = table.find(&format!("<tr data-trolley=\"{tid}\""))?;
    let row = &table[row_start..];
    let row = &row[..row.find("</tr>")?];
    let open = format!("<td class=\"{class}\">");
    let cell = row.find(&open)? + open.len();
    row[cell..].split('<').next()?.trim().parse().ok()
}

/// The number in the fleet table's fruits cell of trolley `tid`, from the rendered DOM.
fn fruits_in_dom(dom: &str, tid: &str) -> Option<u64> {
    number_in_table(dom, "fleet", tid, "fruits")
}

/// The season chart's lines, one per fruit, from the rendered DOM.
fn season_lines_in_dom(dom: &str) -> usize {
    let Some(start) = dom.find("<div id=\"season-chart\">") else {
        return 0;
    };
    let chart = &dom[start..];
    let chart = &chart[..chart.find("</div>").unwrap_or(chart.len())];
    chart.matches("<polyline class=\"season-fruit").count()
}

/// The colours of the swatches in the season's history table, from the rendered DOM.
fn season_swatches_in_dom(dom: &str) -> Vec<[u8; 3]> {
    let Some(start) = dom.find("<table id=\"season-history\">") else {
        return Vec::new();
    };
    let table = &dom[start..];
    let table = &table[..table.find("</table>").unwrap_or(table.len())];
    let hex = |rest: &str| {
        let byte = |i: usize| u8::from_str_radix(rest.get(i..i + 2)?, 16).ok();
        Some([byte(0)?, byte(2)?, byte(4)?])
    };
    table
        .split("data-colour=\"#")
        .skip(1)
        .filter_map(hex)
        .collect()
}

/// Whether the page shows t1 with fruits in its fleet table, and in its season table as many
/// known fruits as its season chart draws lines (both change while late estimates arrive).
fn page_shows_t1_and_its_season(dom: &str) -> bool {
    let known = number_in_table(dom, "season", "t1", "fruits-known");
    fruits_in_dom(dom, "t1").is_some_and(|n| n > 0)
        && known.is_some_and(|n| n > 0 && n as usize == season_lines_in_dom(dom))
}

/// The page's DOM once `ready` holds of it, dumped again until then for at most `secs`
/// seconds; the last dump either way, for the assertions to report.
async fn dom_when(browser: &str, url: &str, secs: u64, ready: fn(&str) -> bool) -> String {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let browser_task = {
            let (browser, url) = (browser.to_owned(), url.to_owned());
            tokio::task::spawn_blocking(move || headless(&browser, &["--dump-dom", &url]))
        };
        let dom = within(60, "chromium --dump-dom", browser_task)
            .await
            .expect("browser task");
        let dom = String::from_utf8_lossy(&dom.stdout).into_owned();
        if ready(&dom) || Instant::now() > deadline {
            return dom;
        }
    }
}

/// A plain HTTP/1.1 GET of `path`: the response's status line and headers (names lowercase, as
/// the server sends them), and its body.
async fn http_get(addr: SocketAddr, path: &str) -> (String, String) {
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    let task = tokio::task::spawn_blocking(move || {
        let mut stream = std::net::TcpStream::connect(addr).expect("connect");
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .expect("read timeout");
        stream.write_all(request.as_bytes()).expect("request sent");
        let mut response = String::new();
        stream.read_to_string(&mut response).expect("response read");
        response
    });
    let response = within(20, "HTTP GET", task).await.expect("HTTP task");
    let (head, body) = response
        .split_once("\r\n\r\n")
        .unwrap_or_else(|| panic!("no end of headers: {response}"));
    (head.to_ascii_lowercase(), body.to_owned())
}

/// The season CSV of t1 downloads as `t1-season.csv` and starts with its header line; an
/// unknown trolley's season is a 404 that says so.
async fn check_season_downloads(addr: SocketAddr) {
    let (head, csv) = http_get(addr, "/api/trolleys/t1/season?format=csv").await;
    assert!(head.starts_with("http/1.1 200"), "season CSV: {head}");
    assert!(
        head.contains("content-type: text/csv"),
        "season CSV: {head}"
    );
    assert!(
        head.contains("content-disposition: attachment; filename=\"t1-season.csv\""),
        "season CSV: {head}"
    );
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("season_id,visit,centre_x_m,centre_y_m,centre_z_m,size_x_m,size_y_m,size_z_m,volume_cm3,seen_this_visit,colour,volume_ratio,growth_cm3"),
        "season CSV: {csv}"
    );
    let records: Vec<_> = lines.collect();
    assert!(!records.is_empty(), "season CSV has no record: {csv}");
    let mut coloured = 0;
    for record in records {
        let fields: Vec<_> = record.split(',').collect();
        assert_eq!(fields.len(), 13, "season CSV line {record:?}");
        // A first visit has no growth measured: no volume ratio, no growth.
        assert_eq!((fields[11], fields[12]), ("", ""), "{record:?}");
        assert!(fields[9] == "true" || fields[9] == "false", "{record:?}");
        // The fruit's colour on the visit, `#rrggbb`, or empty when unknown.
        let colour = fields[10];
        assert!(
            colour.is_empty() || colour.len() == 7 && colour.starts_with('#'),
            "{record:?}"
        );
        coloured += usize::from(!colour.is_empty());
    }
    assert!(coloured > 0, "no record with a colour: {csv}");
    let (head, body) = http_get(addr, "/api/trolleys/nope/season?format=csv").await;
    assert!(head.starts_with("http/1.1 404"), "unknown trolley: {head}");
    assert_eq!(body, "no trolley \"nope\"");
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

    check_season_downloads(addr).await;

    let dom = dom_when(&browser, &url, 90, page_shows_t1_and_its_season).await;
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
    // The season: t1's row with the fruits known, the chart a line per fruit, the downloads.
    let known = number_in_table(&dom, "season", "t1", "fruits-known");
    assert!(
        known.is_some_and(|n| n > 0),
        "season table shows no fruits for t1 (got {known:?}); DOM:\n{dom}"
    );
    assert_eq!(
        season_lines_in_dom(&dom) as u64,
        known.unwrap_or(0),
        "a season line per fruit; DOM:\n{dom}"
    );
    assert!(
        dom.contains("<svg width=\"560\" height=\"260\" data-trolley=\"t1\">"),
        "no season chart for t1"
    );
    for link in ["?format=csv", "?download=1"] {
        let href = format!("href=\"/api/trolleys/t1/season{link}\"");
        assert!(dom.contains(&href), "no season download {href}");
    }
    // The history table: a swatch of each fruit's colour on the visit, red as the fruit are.
    let swatches = season_swatches_in_dom(&dom);
    assert!(
        !swatches.is_empty(),
        "no colour swatch in the season history; DOM:\n{dom}"
    );
    let red = |[r, g, b]: &[u8; 3]| r > g && r > b;
    assert!(
        swatches.iter().all(red),
        "a swatch that is not red: {swatches:?}"
    );

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
