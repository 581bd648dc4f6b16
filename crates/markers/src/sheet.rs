//! A printable sheet of markers: the layout of markers of a family at a true size on
//! A4 or Letter pages, and the sheet as a PDF written here (a few objects, the markers as
//! filled rectangles, captions in the PDF's built-in Helvetica). PDF lengths are exact,
//! so a sheet printed at 100 % (not "fit to page") gives black squares of exactly the
//! size asked for; a 100 mm bar on each page lets one check that with a ruler.
//!
//! Lengths are millimetres with the origin at the page's bottom-left corner, y up (the
//! PDF's own orientation).

use std::fmt::Write as _;
use std::str::FromStr;

use crate::Family;

/// Paper sizes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Paper {
    /// ISO A4, 210 x 297 mm.
    A4,
    /// US Letter, 8.5 x 11 in (215.9 x 279.4 mm).
    Letter,
}

impl Paper {
    /// Width and height, millimetres.
    pub fn size_mm(self) -> [f64; 2] {
        match self {
            Self::A4 => [210.0, 297.0],
            Self::Letter => [215.9, 279.4],
        }
    }
}

impl FromStr for Paper {
    type Err = SheetError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "a4" => Ok(Self::A4),
            "letter" => Ok(Self::Letter),
            _ => Err(SheetError::Paper(s.to_owned())),
        }
    }
}

/// Why a sheet cannot be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SheetError {
    /// An unknown paper size.
    #[error("unknown paper {0:?}: a4 or letter")]
    Paper(String),
    /// A marker id outside the family.
    #[error("{family} has markers 0 to {last}; {id} is not one")]
    Id {
        /// The family.
        family: Family,
        /// The last id it has.
        last: u32,
        /// The id asked for.
        id: u32,
    },
    /// No marker asked for.
    #[error("no marker ids given")]
    NoIds,
    /// A size that is not a positive number, or one that does not fit on the paper.
    #[error(
        "a {size_mm} mm marker does not fit on {paper:?} paper with its white border: at most {max_mm:.0} mm"
    )]
    Size {
        /// The black square's side asked for, mm.
        size_mm: f64,
        /// The paper.
        paper: Paper,
        /// The largest that fits, mm.
        max_mm: f64,
    },
}

/// Nothing is printed closer than this to the paper's edge (most printers cannot).
pub const EDGE_MM: f64 = 5.0;
/// Space between two markers' white borders.
const GAP_MM: f64 = 3.0;
/// Room below each marker for its caption.
const CAPTION_MM: f64 = 6.0;
/// Room at the bottom of each page for the scale bar and the printing note.
const FOOTER_MM: f64 = 14.0;
/// The scale bar's length.
pub const BAR_MM: f64 = 100.0;
/// The scale bar's height above the paper's bottom edge: clear of a half-inch (12.7 mm)
/// printer margin, so that the one check of the true size is printed (it was 7 mm).
pub const BAR_FROM_EDGE_MM: f64 = 13.0;

/// One marker on a page.
#[derive(Debug, Clone, PartialEq)]
pub struct Placed {
    /// Its id.
    pub id: u32,
    /// The bottom-left corner of its black square, mm.
    pub black_origin_mm: [f64; 2],
}

/// Markers of one family and size laid out on pages.
#[derive(Debug, Clone, PartialEq)]
pub struct Sheet {
    /// The family.
    pub family: Family,
    /// The side of each marker's black square, mm.
    pub size_mm: f64,
    /// The paper.
    pub paper: Paper,
    /// The markers of each page.
    pub pages: Vec<Vec<Placed>>,
}

impl Sheet {
    /// Lays out markers `ids` of `family` with black squares of `size_m` metres on
    /// `paper`, as many per page as fit (in rows, from the top left), each with its white
    /// border (one cell wide) clear of the others and of the paper's [`EDGE_MM`].
    pub fn layout(
        family: Family,
        ids: &[u32],
        size_m: f64,
        paper: Paper,
    ) -> Result<Self, SheetError> {
        if ids.is_empty() {
            return Err(SheetError::NoIds);
        }
        let last = family.ids() - 1;
        if let Some(&id) = ids.iter().find(|&&id| id > last) {
            return Err(SheetError::Id { family, last, id });
        }
        let pattern = family.pattern(0).ok_or(SheetError::NoIds)?;
        let ratio = pattern.cells as f64 / pattern.black_cells as f64;
        let size_mm = size_m * 1000.0;
        let [w, h] = paper.size_mm();
        let (room_w, room_h) = (
            w - 2.0 * EDGE_MM,
            h - 2.0 * EDGE_MM - FOOTER_MM - CAPTION_MM,
        );
        let max_mm = room_w.min(room_h) / ratio;
        let outer = size_mm * ratio;
        if !(size_mm.is_finite() && size_mm > 0.0) || outer > room_w + 1e-9 || outer > room_h + 1e-9
        {
            return Err(SheetError::Size {
                size_mm,
                paper,
                max_mm,
            });
        }
        let cols = (((room_w + GAP_MM) / (outer + GAP_MM)).floor() as usize).max(1);
        let rows = (((room_h + CAPTION_MM + GAP_MM) / (outer + CAPTION_MM + GAP_MM)).floor()
            as usize)
            .max(1);
        let ring = (outer - size_mm) / 2.0;
        let grid_w = cols as f64 * outer + (cols - 1) as f64 * GAP_MM;
        let left = (w - grid_w) / 2.0;
        let top = h - EDGE_MM;
        let pages = ids
            .chunks(cols * rows)
            .map(|page| {
                page.iter()
                    .enumerate()
                    .map(|(i, &id)| {
                        let (row, col) = (i / cols, i % cols);
                        let x = left + col as f64 * (outer + GAP_MM) + ring;
                        let outer_top = top - row as f64 * (outer + CAPTION_MM + GAP_MM);
                        let y = outer_top - ring - size_mm;
                        Placed {
                            id,
                            black_origin_mm: [x, y],
                        }
                    })
                    .collect()
            })
            .collect();
        Ok(Self {
            family,
            size_mm,
            paper,
            pages,
        })
    }

    /// Where the markers of a one-page sheet lie relative to each other once the page is
    /// laid flat: each id and its centre in metres from the first marker's centre, x to
    /// the right and y up the page (the frame `calibrate --map` reads, every marker's yaw
    /// 0). `None` for a sheet of several pages, whose markers lie as the user lays them.
    pub fn map(&self) -> Option<Vec<(u32, [f64; 2])>> {
        let [page] = self.pages.as_slice() else {
            return None;
        };
        let half = self.size_mm / 2.0;
        let centre = |p: &Placed| [p.black_origin_mm[0] + half, p.black_origin_mm[1] + half];
        let origin = centre(page.first()?);
        Some(
            page.iter()
                .map(|p| {
                    let c = centre(p);
                    (
                        p.id,
                        [(c[0] - origin[0]) / 1000.0, (c[1] - origin[1]) / 1000.0],
                    )
                })
                .collect(),
        )
    }

    /// The black rectangles of marker `placed`: `[x, y, width, height]` in mm, a run of
    /// black cells of one row each.
    pub fn black_rects(&self, placed: &Placed) -> Vec<[f64; 4]> {
        let pattern = self
            .family
            .pattern(placed.id)
            .expect("the layout checked the id");
        let cell = self.size_mm / pattern.black_cells as f64;
        let ring = (pattern.cells - pattern.black_cells) / 2;
        // The pattern's top-left corner, with its white ring.
        let x0 = placed.black_origin_mm[0] - ring as f64 * cell;
        let top = placed.black_origin_mm[1] + self.size_mm + ring as f64 * cell;
        let mut out = Vec::new();
        for row in 0..pattern.cells {
            let mut col = 0;
            while col < pattern.cells {
                if pattern.is_white(col, row) {
                    col += 1;
                    continue;
                }
                let start = col;
                while col < pattern.cells && !pattern.is_white(col, row) {
                    col += 1;
                }
                out.push([
                    x0 + start as f64 * cell,
                    top - (row + 1) as f64 * cell,
                    (col - start) as f64 * cell,
                    cell,
                ]);
            }
        }
        out
    }

    /// The sheet as a PDF document.
    pub fn pdf(&self) -> Vec<u8> {
        let [w, h] = self.paper.size_mm();
        let pt = |mm: f64| mm * 72.0 / 25.4;
        // Objects 1 (catalog), 2 (pages), 3 (font), then a page and its contents each.
        let mut objects: Vec<String> = vec![
            "<< /Type /Catalog /Pages 2 0 R >>".into(),
            String::new(),
            "<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>"
                .into(),
        ];
        let mut kids = Vec::new();
        for (n, page) in self.pages.iter().enumerate() {
            let content = self.page_content(page, n + 1);
            let page_obj = objects.len() + 1;
            kids.push(format!("{page_obj} 0 R"));
            objects.push(format!(
                "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {} {}] /Resources << /Font << /F1 3 0 R >> >> /Contents {} 0 R >>",
                num(pt(w)),
                num(pt(h)),
                page_obj + 1
            ));
            objects.push(format!(
                "<< /Length {} >>\nstream\n{content}endstream",
                content.len()
            ));
        }
        objects[1] = format!(
            "<< /Type /Pages /Kids [{}] /Count {} >>",
            kids.join(" "),
            kids.len()
        );
        let mut out = String::from("%PDF-1.4\n");
        let mut offsets = Vec::with_capacity(objects.len());
        for (i, body) in objects.iter().enumerate() {
            offsets.push(out.len());
            let _ = write!(out, "{} 0 obj\n{body}\nendobj\n", i + 1);
        }
        let xref = out.len();
        let _ = write!(out, "xref\n0 {}\n0000000000 65535 f \n", objects.len() + 1);
        for o in offsets {
            let _ = writeln!(out, "{o:010} 00000 n ");
        }
        let _ = write!(
            out,
            "trailer\n<< /Size {} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n",
            objects.len() + 1
        );
        out.into_bytes()
    }

    /// One page's content stream: in millimetres (the first operator scales points to
    /// them), the markers, their captions, the scale bar and the note.
    fn page_content(&self, page: &[Placed], number: usize) -> String {
        let [w, _] = self.paper.size_mm();
        let mut s = String::new();
        // Points per millimetre, to 1e-9: a 160 mm square is then right to a nanometre.
        let scale = format!("{:.9}", 72.0 / 25.4);
        let _ = writeln!(s, "{scale} 0 0 {scale} 0 0 cm");
        s.push_str("0 g\n");
        for placed in page {
            for [x, y, rw, rh] in self.black_rects(placed) {
                let _ = writeln!(s, "{} {} {} {} re", num(x), num(y), num(rw), num(rh));
            }
            s.push_str("f\n");
            let [x, y] = placed.black_origin_mm;
            let ring = self.size_mm / 8.0;
            text(
                &mut s,
                x,
                y - ring - 4.0,
                3.0,
                &format!(
                    "{} id {}, black square {} mm",
                    self.family,
                    placed.id,
                    num(self.size_mm)
                ),
            );
        }
        // The scale bar: BAR_MM long, with end ticks.
        let bar_x = (w - BAR_MM) / 2.0;
        let bar_y = BAR_FROM_EDGE_MM;
        let _ = writeln!(
            s,
            "{} {} {} 0.6 re {} {} 0.3 2.5 re {} {} 0.3 2.5 re f",
            num(bar_x),
            num(bar_y),
            num(BAR_MM),
            num(bar_x),
            num(bar_y),
            num(bar_x + BAR_MM - 0.3),
            num(bar_y)
        );
        // The note under the bar, within the footer.
        text(
            &mut s,
            bar_x,
            bar_y - 4.5,
            2.8,
            &format!(
                "Print at 100 % (not fit to page): this bar is 100 mm. Page {number} of {}.",
                self.pages.len()
            ),
        );
        s
    }
}

/// A line of text at (`x`, `y`) mm, `size` mm high, in Helvetica.
fn text(s: &mut String, x: f64, y: f64, size: f64, line: &str) {
    let escaped: String = line
        .chars()
        .flat_map(|c| match c {
            '(' | ')' | '\\' => vec!['\\', c],
            c if c.is_ascii() => vec![c],
            _ => vec!['?'],
        })
        .collect();
    let _ = writeln!(
        s,
        "BT /F1 {} Tf {} {} Td ({escaped}) Tj ET",
        num(size),
        num(x),
        num(y)
    );
}

/// A number as PDF writes it: at most 4 decimals, no trailing zeros.
fn num(v: f64) -> String {
    let t = format!("{v:.4}");
    let t = t.trim_end_matches('0').trim_end_matches('.');
    if t == "-0" { "0".into() } else { t.into() }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Page `n` drawn at `dpi` as gray bytes (white 255, black 0), from the rectangles
    /// the PDF fills: width, height and pixels.
    fn raster(sheet: &Sheet, n: usize, dpi: f64) -> (usize, usize, Vec<u8>) {
        let [w, h] = sheet.paper.size_mm();
        let px = |mm: f64| mm / 25.4 * dpi;
        let (wp, hp) = (px(w).round() as usize, px(h).round() as usize);
        let mut image = vec![255u8; wp * hp];
        for placed in &sheet.pages[n] {
            for [x, y, rw, rh] in sheet.black_rects(placed) {
                let (c0, c1) = (px(x).round() as usize, px(x + rw).round() as usize);
                // Image rows run downwards from the page's top.
                let (r0, r1) = (px(h - y - rh).round() as usize, px(h - y).round() as usize);
                for r in r0..r1 {
                    image[r * wp + c0..r * wp + c1].fill(0);
                }
            }
        }
        (wp, hp, image)
    }

    /// Issue 51, item 13: the 100 mm bar stands clear of a half-inch printer margin (it
    /// was 7 mm from the edge), its note below it, both within the footer.
    #[test]
    fn the_scale_bar_is_clear_of_the_printers_margin() {
        for paper in [Paper::A4, Paper::Letter] {
            let sheet = Sheet::layout(Family::Tag36h11, &[0, 1, 2, 3], 0.16, paper).expect("fits");
            let content = sheet.page_content(&sheet.pages[0], 1);
            let bar = content
                .lines()
                .find(|l| l.contains(&format!(" {} 0.6 re ", num(BAR_MM))))
                .expect("the bar");
            let y: f64 = bar.split_whitespace().nth(1).unwrap().parse().unwrap();
            assert!((12.7..EDGE_MM + FOOTER_MM - 2.5).contains(&y), "{bar}");
            // Every marker's caption and border stay above the footer.
            for placed in &sheet.pages[0] {
                assert!(
                    placed.black_origin_mm[1] > EDGE_MM + FOOTER_MM,
                    "{placed:?}"
                );
            }
        }
    }

    #[test]
    fn sixteen_centimetre_markers_fit_one_per_a4_page_and_are_detected_at_true_size() {
        let sheet = Sheet::layout(Family::Tag36h11, &[0, 1, 2, 3], 0.16, Paper::A4).expect("fits");
        assert_eq!(sheet.pages.len(), 4);
        let dpi = 50.0;
        for (n, page) in sheet.pages.iter().enumerate() {
            let (w, h, image) = raster(&sheet, n, dpi);
            let found = crate::detect(Family::Tag36h11, &image, w, h).expect("detection runs");
            assert_eq!(found.len(), 1, "page {n}: {found:?}");
            assert_eq!(found[0].id, page[0].id);
            let c = found[0].corners;
            let side_px = ((c[1][0] - c[0][0]).powi(2) + (c[1][1] - c[0][1]).powi(2)).sqrt();
            let want = 160.0 / 25.4 * dpi;
            assert!((side_px - want).abs() < 2.0, "{side_px} px, want {want}");
        }
    }

    #[test]
    fn small_markers_share_a_page_and_each_is_found() {
        let ids: Vec<u32> = (10..40).collect();
        let sheet = Sheet::layout(Family::Tag36h11, &ids, 0.03, Paper::Letter).expect("fits");
        let on_first = sheet.pages[0].len();
        assert!(on_first > 20, "{on_first}");
        let (w, h, image) = raster(&sheet, 0, 150.0);
        let mut found: Vec<u32> = crate::detect(Family::Tag36h11, &image, w, h)
            .expect("detection runs")
            .iter()
            .map(|d| d.id)
            .collect();
        found.sort_unstable();
        let want: Vec<u32> = sheet.pages[0].iter().map(|p| p.id).collect();
        assert_eq!(found, want);
    }

    #[test]
    fn what_does_not_fit_is_refused_with_the_largest_that_does() {
        let e = Sheet::layout(Family::Tag36h11, &[0], 0.17, Paper::A4).expect_err("too large");
        assert!(e.to_string().contains("at most 160 mm"), "{e}");
        assert!(Sheet::layout(Family::Tag36h11, &[587], 0.05, Paper::A4).is_err());
        assert!(Sheet::layout(Family::Tag36h11, &[], 0.05, Paper::A4).is_err());
        assert!(Sheet::layout(Family::Tag36h11, &[0], -0.05, Paper::A4).is_err());
    }

    #[test]
    fn the_pdf_is_well_formed_and_its_cross_references_point_at_its_objects() {
        let sheet = Sheet::layout(Family::Tag36h11, &[0, 1], 0.16, Paper::A4).expect("fits");
        let pdf = sheet.pdf();
        let text = String::from_utf8(pdf).expect("ASCII");
        assert!(text.starts_with("%PDF-1.4\n") && text.ends_with("%%EOF\n"));
        let xref: usize = text
            .rsplit("startxref\n")
            .next()
            .and_then(|t| t.lines().next())
            .and_then(|n| n.parse().ok())
            .expect("startxref");
        assert!(text[xref..].starts_with("xref\n"));
        let entries: Vec<usize> = text[xref..]
            .lines()
            .skip(3)
            .take_while(|l| l.ends_with(" n "))
            .map(|l| l[..10].parse().expect("an offset"))
            .collect();
        assert_eq!(entries.len(), 3 + 2 * 2);
        for (i, offset) in entries.iter().enumerate() {
            assert!(
                text[*offset..].starts_with(&format!("{} 0 obj\n", i + 1)),
                "object {}",
                i + 1
            );
        }
        // A4 in points, and the scale from points to millimetres.
        assert!(text.contains("/MediaBox [0 0 595.2756 841.8898]"), "{text}");
        assert!(text.contains("2.834645669 0 0 2.834645669 0 0 cm"));
        for stream in text.split(">>\nstream\n").skip(1) {
            let (body, _) = stream.split_once("endstream").expect("its end");
            assert!(text.contains(&format!("/Length {}", body.len())));
        }
    }
}
