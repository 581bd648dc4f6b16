//! `coapcam markers` writes a sheet that prints at the true size: the PDF is rendered by
//! a renderer of its own (poppler's pdftoppm, as a printer driver would), and the
//! calibration's detector finds each marker on its page, with its id and its black
//! square as wide as asked for at the rendering's resolution. A page's map (`--map`)
//! calibrates a camera that sees the page on the table.

use std::process::Command;

use crate::support::{COAPCAM, LIMIT, Peer, Proc, SN, TempDir, available, serve_with};

/// Reads a binary PGM (P5, 8-bit) as pdftoppm -gray writes it: width, height, pixels.
fn pgm(bytes: &[u8]) -> (usize, usize, Vec<u8>) {
    // The header: magic, width, height, maxval, each after whitespace; then one byte of
    // whitespace and the pixels.
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        fields.push(String::from_utf8_lossy(&bytes[start..at]).into_owned());
    }
    assert_eq!(fields[0], "P5", "not a binary PGM");
    assert_eq!(fields[3], "255", "not 8-bit");
    let (w, h): (usize, usize) = (
        fields[1].parse().expect("a width"),
        fields[2].parse().expect("a height"),
    );
    let pixels = bytes[at + 1..].to_vec();
    assert_eq!(pixels.len(), w * h);
    (w, h, pixels)
}

#[test]
fn the_printed_sheet_has_each_marker_at_its_true_size() {
    if !available(
        "markers::the_printed_sheet_has_each_marker_at_its_true_size",
        &[Peer::Poppler],
    ) {
        return;
    }
    let dir = TempDir::new("markers-sheet");
    let pdf = dir.join("sheet.pdf");
    let pdf = pdf.to_str().expect("UTF-8 path");
    Proc::run(
        COAPCAM,
        &[
            "markers", "--family", "tag36h11", "--ids", "0-3", "--size", "0.16", "-o", pdf,
        ],
        LIMIT,
    )
    .expect_success("coapcam markers");
    let dpi = 100.0;
    let prefix = dir.join("page");
    let rendered = Command::new("pdftoppm")
        .args(["-r", "100", "-gray", pdf])
        .arg(&prefix)
        .status()
        .expect("running pdftoppm");
    assert!(rendered.success(), "pdftoppm failed on the sheet");
    // The black square's side in pixels at this resolution.
    let want = 0.16 / 0.0254 * dpi;
    for (page, id) in (1..=4).zip(0u32..) {
        let file = dir.join(&format!("page-{page}.pgm"));
        let (w, h, pixels) = pgm(&std::fs::read(&file).expect("a rendered page"));
        // A4 at 100 dpi: 826.8 x 1169.3 pixels, rounded either way.
        assert!(
            w.abs_diff(827) <= 1 && h.abs_diff(1169) <= 1,
            "page {page}: {w} x {h}"
        );
        let found =
            ::markers::detect(::markers::Family::Tag36h11, &pixels, w, h).expect("detection runs");
        assert_eq!(found.len(), 1, "page {page}: {found:?}");
        assert_eq!(found[0].id, id, "page {page}");
        let c = found[0].corners;
        for i in 0..4 {
            let (a, b) = (c[i], c[(i + 1) % 4]);
            let side = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            assert!(
                (side - want).abs() < 1.5,
                "page {page}: a side of {side:.1} px, want {want:.1} px (0.16 m at {dpi} dpi)"
            );
        }
    }
    assert!(!dir.join("page-5.pgm").exists(), "more pages than markers");
}

/// A page of `coapcam markers` laid on the table calibrates a camera with the map the
/// command wrote: the synthetic camera draws the page's markers where the sheet puts
/// them (the sheet turned and moved on the table), `calibrate --map` finds them all and
/// places the camera in marker 0's frame.
#[test]
fn a_printed_page_and_its_map_calibrate_a_camera() {
    let dir = TempDir::new("markers-map");
    let (pdf, map) = (dir.join("page.pdf"), dir.join("page.toml"));
    let (pdf, map) = (
        pdf.to_str().expect("UTF-8 path"),
        map.to_str().expect("UTF-8 path"),
    );
    Proc::run(
        COAPCAM,
        &[
            "markers", "--ids", "0-3", "--size", "0.07", "-o", pdf, "--map", map,
        ],
        LIMIT,
    )
    .expect_success("coapcam markers --map");
    // The map is a scene file of markers alone.
    let sheet = rgbd::Scene::load(std::path::Path::new(map)).expect("the map reads as a scene");
    assert_eq!(sheet.markers.len(), 4, "{:?}", sheet.markers);
    // The page lies turned by 25 degrees, marker 0 at (-0.1, 0.05).
    let (yaw, at) = (25.0_f64, [-0.1, 0.05]);
    let (sin, cos) = yaw.to_radians().sin_cos();
    let camera = [0.35, -0.30, 0.95];
    let mut scene = format!(
        "seed = 3\n[[camera]]\nserial = \"{SN}\"\nposition = {camera:?}\n\
         look_at = [0.0, 0.0, 0.0]\nnoise = \"d415\"\ncalibrated = false\n"
    );
    for m in &sheet.markers {
        assert_eq!(m.yaw_deg, 0.0);
        let c = m.center;
        let world = [
            at[0] + cos * c[0] - sin * c[1],
            at[1] + sin * c[0] + cos * c[1],
        ];
        scene += &format!(
            "[[marker]]\nfamily = \"{}\"\nid = {}\nsize = {}\ncenter = {world:?}\nyaw_deg = {yaw}\n",
            m.family, m.id, m.size
        );
    }
    let scene_file = dir.join("table.toml");
    std::fs::write(&scene_file, scene).expect("the scene");
    let (_server, addr) = serve_with(
        dir.path(),
        &["--scene", scene_file.to_str().expect("UTF-8 path")],
    );
    let report = Proc::run(
        COAPCAM,
        &[
            "calibrate",
            "--server",
            &format!("coap://{addr}"),
            "--map",
            map,
            "--json",
        ],
        LIMIT,
    )
    .expect_success("calibrate --map")
    .json();
    assert_eq!(
        report["markers"],
        serde_json::json!([0, 1, 2, 3]),
        "{report}"
    );
    // The camera seen from marker 0, whose axes are the page's.
    let (dx, dy) = (camera[0] - at[0], camera[1] - at[1]);
    let truth = [cos * dx + sin * dy, -sin * dx + cos * dy, camera[2]].map(|v| v * 1000.0);
    for (i, want) in truth.iter().enumerate() {
        let got = report["camera_mm"][i].as_f64().expect("a position");
        assert!(
            (got - want).abs() < 3.0,
            "axis {i}: {got:.1} mm, truth {want:.1} mm: {report}"
        );
    }
}
