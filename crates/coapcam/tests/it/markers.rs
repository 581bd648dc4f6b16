//! `coapcam markers` writes a sheet that prints at the true size: the PDF is rendered by
//! a renderer of its own (poppler's pdftoppm, as a printer driver would), and the
//! calibration's detector finds each marker on its page, with its id and its black
//! square as wide as asked for at the rendering's resolution.

use std::process::Command;

use crate::support::{COAPCAM, LIMIT, Peer, Proc, TempDir, available};

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
