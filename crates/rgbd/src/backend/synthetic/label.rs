//! Barcode labels as textures: modules from the `qrcode` and `barcoders` encoders (QR,
//! Code 128) and from rxing's (Data Matrix, EAN-13, UPC-A, PDF417).

use serde::Deserialize;

/// Kind of barcode on a label.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LabelKind {
    /// A QR code.
    Qr,
    /// A Code 128 bar code (ASCII text).
    Code128,
    /// A Data Matrix (ECC 200) code.
    #[serde(rename = "datamatrix")]
    DataMatrix,
    /// An EAN-13 bar code: 13 digits, the last the check digit.
    Ean13,
    /// A UPC-A bar code: 12 digits, the last the check digit.
    Upca,
    /// A PDF417 code.
    Pdf417,
}

impl LabelKind {
    /// Every kind, in the order the scene files document them.
    pub const ALL: [Self; 6] = [
        Self::Qr,
        Self::Code128,
        Self::DataMatrix,
        Self::Ean13,
        Self::Upca,
        Self::Pdf417,
    ];

    /// Whether the code is a row of bars (its modules are columns across the label).
    pub fn is_linear(self) -> bool {
        matches!(self, Self::Code128 | Self::Ean13 | Self::Upca)
    }
}

/// A barcode label on a box's top face.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Label {
    /// Barcode kind.
    pub kind: LabelKind,
    /// Encoded text.
    pub text: String,
    /// Label width in metres.
    pub size: f64,
    /// When it is stuck on the box, seconds of scene time; `None` = from the start.
    #[serde(default)]
    pub appear_s: Option<f64>,
    /// When it is peeled off; `None` = never.
    #[serde(default)]
    pub remove_s: Option<f64>,
}

impl Label {
    /// Label extent on the top face, metres: (along the box length, along its width). A
    /// bar code is half as tall as it is long; a 2D code's modules are square.
    pub fn extent_m(&self) -> (f64, f64) {
        match self.kind {
            LabelKind::Qr => (self.size, self.size),
            k if k.is_linear() => (self.size, self.size / 2.0),
            // A text that cannot be encoded is refused by the scene's validation.
            _ => encode(self).map_or((self.size, self.size), |t| {
                (self.size, self.size * t.rows as f64 / t.columns as f64)
            }),
        }
    }

    /// How many modules the label spans along its width, quiet zones included: `size`
    /// over this is the module's width.
    pub fn modules_across(&self) -> Result<usize, String> {
        encode(self).map(|t| t.columns)
    }
}

/// QR quiet zone, modules (ISO/IEC 18004: 4).
const QR_QUIET: usize = 4;
/// Code 128 quiet zone on each side, modules (ISO/IEC 15417: 10).
const CODE128_QUIET: usize = 10;
/// Blank margin above and below Code 128 bars, as a fraction of the label height.
const CODE128_MARGIN: f32 = 0.12;
/// EAN-13 and UPC-A quiet zone on each side, modules (ISO/IEC 15420: 11 and 7; the
/// larger on both).
const EAN_QUIET: usize = 11;
/// Data Matrix quiet zone, modules (ISO/IEC 16022: 1; two here).
const DATAMATRIX_QUIET: usize = 2;
/// PDF417 quiet zone, modules (ISO/IEC 15438: 2).
const PDF417_QUIET: usize = 2;

/// A label's black/white modules over its rectangle.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LabelTexture {
    /// Columns (along the label's width).
    columns: usize,
    /// Rows (along the label's height); 1 for a linear bar code.
    rows: usize,
    /// `true` = black, row-major.
    dark: Vec<bool>,
    /// Fraction of the height left blank above and below the modules.
    margin: f32,
}

impl LabelTexture {
    /// Whether the label is black at (`u`, `v`), both in [0, 1) across the label's
    /// width and height.
    pub(crate) fn is_dark(&self, u: f32, v: f32) -> bool {
        if v < self.margin || v >= 1.0 - self.margin || !(0.0..1.0).contains(&u) {
            return false;
        }
        let v = (v - self.margin) / (1.0 - 2.0 * self.margin);
        let col = ((u * self.columns as f32) as usize).min(self.columns - 1);
        let row = ((v * self.rows as f32) as usize).min(self.rows - 1);
        self.dark[row * self.columns + col]
    }
}

/// Encodes a label's text; the error says why the text cannot be encoded.
pub(crate) fn encode(label: &Label) -> Result<LabelTexture, String> {
    match label.kind {
        LabelKind::Qr => {
            let code = qrcode::QrCode::new(label.text.as_bytes())
                .map_err(|e| format!("cannot encode {:?} as QR: {e}", label.text))?;
            let width = code.width();
            let modules = code.to_colors();
            let side = width + 2 * QR_QUIET;
            let mut dark = vec![false; side * side];
            for (i, m) in modules.iter().enumerate() {
                let (row, col) = (i / width + QR_QUIET, i % width + QR_QUIET);
                dark[row * side + col] = *m == qrcode::Color::Dark;
            }
            Ok(LabelTexture {
                columns: side,
                rows: side,
                dark,
                margin: 0.0,
            })
        }
        LabelKind::DataMatrix => {
            let m = rxing_matrix(label, rxing::BarcodeFormat::DATA_MATRIX, "Data Matrix")?;
            Ok(square_cells(&m, DATAMATRIX_QUIET))
        }
        LabelKind::Pdf417 => {
            // rxing draws each PDF417 row 4 modules tall (the standard asks for 3 or more).
            let m = rxing_matrix(label, rxing::BarcodeFormat::PDF_417, "PDF417")?;
            Ok(square_cells(&m, PDF417_QUIET))
        }
        LabelKind::Ean13 | LabelKind::Upca => {
            let (digits, format, name) = if label.kind == LabelKind::Ean13 {
                (13, rxing::BarcodeFormat::EAN_13, "EAN-13")
            } else {
                (12, rxing::BarcodeFormat::UPC_A, "UPC-A")
            };
            if label.text.len() != digits || !label.text.bytes().all(|b| b.is_ascii_digit()) {
                return Err(format!(
                    "{name} text must be {digits} digits (the last the check digit), got {:?}",
                    label.text
                ));
            }
            let m = rxing_matrix(label, format, name)?;
            Ok(bars(&m, EAN_QUIET))
        }
        LabelKind::Code128 => {
            if label.text.is_empty() || !label.text.bytes().all(|b| (32..=126).contains(&b)) {
                return Err(format!(
                    "Code 128 text must be 1 or more printable ASCII characters, got {:?}",
                    label.text
                ));
            }
            // Character set B covers printable ASCII.
            let code = barcoders::sym::code128::Code128::new(format!("\u{0181}{}", label.text))
                .map_err(|e| format!("cannot encode {:?} as Code 128: {e}", label.text))?;
            let bars = code.encode();
            let columns = bars.len() + 2 * CODE128_QUIET;
            let mut dark = vec![false; columns];
            for (i, b) in bars.iter().enumerate() {
                dark[i + CODE128_QUIET] = *b == 1;
            }
            Ok(LabelTexture {
                columns,
                rows: 1,
                dark,
                margin: CODE128_MARGIN,
            })
        }
    }
}

/// The modules of `label`'s text in `format`, one bit a module, without quiet zone.
fn rxing_matrix(
    label: &Label,
    format: rxing::BarcodeFormat,
    name: &str,
) -> Result<rxing::common::BitMatrix, String> {
    use rxing::Writer as _;
    let hints = rxing::EncodeHints {
        Margin: Some("0".into()),
        ..Default::default()
    };
    rxing::MultiFormatWriter
        .encode_with_hints(&label.text, &format, 0, 0, &hints)
        .map_err(|e| format!("cannot encode {:?} as {name}: {e}", label.text))
}

/// A 2D code's modules with `quiet` modules of white around them.
fn square_cells(m: &rxing::common::BitMatrix, quiet: usize) -> LabelTexture {
    let (w, h) = (m.getWidth() as usize, m.getHeight() as usize);
    let (columns, rows) = (w + 2 * quiet, h + 2 * quiet);
    let mut dark = vec![false; columns * rows];
    for y in 0..h {
        for x in 0..w {
            dark[(y + quiet) * columns + x + quiet] = m.get(x as u32, y as u32);
        }
    }
    LabelTexture {
        columns,
        rows,
        dark,
        margin: 0.0,
    }
}

/// A bar code's bars (the matrix's first row) with `quiet` modules of white each side.
fn bars(m: &rxing::common::BitMatrix, quiet: usize) -> LabelTexture {
    let w = m.getWidth() as usize;
    let columns = w + 2 * quiet;
    let mut dark = vec![false; columns];
    for x in 0..w {
        dark[x + quiet] = m.get(x as u32, 0);
    }
    LabelTexture {
        columns,
        rows: 1,
        dark,
        margin: CODE128_MARGIN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn qr_label_has_a_white_quiet_zone_and_dark_finder_corner() {
        let t = encode(&Label {
            kind: LabelKind::Qr,
            text: "PKG-0001".into(),
            size: 0.08,
            appear_s: None,
            remove_s: None,
        })
        .unwrap();
        assert!(!t.is_dark(0.01, 0.01));
        // The top-left finder pattern starts right after the quiet zone.
        let m = 1.0 / t.columns as f32;
        assert!(t.is_dark((QR_QUIET as f32 + 0.5) * m, (QR_QUIET as f32 + 0.5) * m));
    }

    #[test]
    fn code128_refuses_non_ascii() {
        let e = encode(&Label {
            kind: LabelKind::Code128,
            text: "Größe".into(),
            size: 0.1,
            appear_s: None,
            remove_s: None,
        });
        assert!(e.unwrap_err().contains("printable ASCII"));
    }

    #[test]
    fn every_kind_encodes_with_its_quiet_zone() {
        for (kind, text) in [
            (LabelKind::DataMatrix, "PKG-0001"),
            (LabelKind::Pdf417, "1Z999AA10123456784"),
            (LabelKind::Ean13, "4006381333931"),
            (LabelKind::Upca, "036000291452"),
        ] {
            let label = Label {
                kind,
                text: text.into(),
                size: 0.1,
                appear_s: None,
                remove_s: None,
            };
            let t = encode(&label).unwrap();
            let dark = t.dark.iter().filter(|&&d| d).count();
            assert!(
                dark > 10 && dark < t.dark.len() / 2 + 200,
                "{kind:?}: {dark}"
            );
            // The corners are quiet, and some module just inside the quiet zone is dark.
            assert!(!t.is_dark(0.001, 0.5) && !t.is_dark(0.999, 0.5), "{kind:?}");
            let (lx, ly) = label.extent_m();
            assert!(lx == 0.1 && ly > 0.0 && ly <= 0.1, "{kind:?}: {lx} x {ly}");
        }
    }

    #[test]
    fn ean_and_upc_take_their_digits_with_the_check_digit_only() {
        for (kind, text) in [
            (LabelKind::Ean13, "400638133393"),
            (LabelKind::Upca, "03600029145X"),
        ] {
            let e = encode(&Label {
                kind,
                text: text.into(),
                size: 0.1,
                appear_s: None,
                remove_s: None,
            });
            assert!(e.unwrap_err().contains("digits"), "{kind:?}");
        }
        // A wrong check digit.
        assert!(
            encode(&Label {
                kind: LabelKind::Ean13,
                text: "4006381333932".into(),
                size: 0.1,
                appear_s: None,
                remove_s: None,
            })
            .is_err()
        );
    }
}
