//! Barcode labels as textures: modules from the `qrcode` and `barcoders` encoders.

use serde::Deserialize;

/// Kind of barcode on a label.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LabelKind {
    /// A QR code.
    Qr,
    /// A Code 128 bar code (ASCII text).
    Code128,
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
    /// Label extent on the top face, metres: (along the box length, along its width).
    pub fn extent_m(&self) -> (f64, f64) {
        match self.kind {
            LabelKind::Qr => (self.size, self.size),
            LabelKind::Code128 => (self.size, self.size / 2.0),
        }
    }
}

/// QR quiet zone, modules (ISO/IEC 18004: 4).
const QR_QUIET: usize = 4;
/// Code 128 quiet zone on each side, modules (ISO/IEC 15417: 10).
const CODE128_QUIET: usize = 10;
/// Blank margin above and below Code 128 bars, as a fraction of the label height.
const CODE128_MARGIN: f32 = 0.12;

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
}
