//! The plot of `bench transfer`: one panel per size, each mode's median time against the
//! link's loss rate on a log scale, with the fastest and slowest run as a bar.

use image::{Rgb, RgbImage};

use super::config::{Link, Mode};
use super::runs::Cell;
use crate::stats::Spread;
use crate::vision::picture;

/// Width and height of one size's panel, pixels.
const PANEL: (u32, u32) = (600, 450);
/// Width of the legend on the right, pixels.
const LEGEND_WIDTH: u32 = 300;
/// The plot area inside a panel: left, top, right, bottom margins.
const MARGIN: (u32, u32, u32, u32) = (72, 44, 20, 56);
const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const INK: Rgb<u8> = Rgb([30, 30, 30]);
const GRID: Rgb<u8> = Rgb([215, 215, 215]);
const MINOR_GRID: Rgb<u8> = Rgb([238, 238, 238]);

/// A point's shape: which link it was measured on.
#[derive(Debug, Clone, Copy)]
enum Marker {
    Circle,
    Square,
    Triangle,
    Diamond,
}

/// A canvas with the few primitives the plot needs, clipped to the image.
struct Canvas(RgbImage);

impl Canvas {
    fn dot(&mut self, x: i64, y: i64, color: Rgb<u8>) {
        if let (Ok(x), Ok(y)) = (u32::try_from(x), u32::try_from(y))
            && x < self.0.width()
            && y < self.0.height()
        {
            self.0.put_pixel(x, y, color);
        }
    }

    /// A line `width` pixels thick.
    fn line(&mut self, from: (i64, i64), to: (i64, i64), width: u32, color: Rgb<u8>) {
        let point = |(x, y): (i64, i64)| [x as f32, y as f32];
        picture::draw_line(&mut self.0, point(from), point(to), color, width);
    }

    fn marker(&mut self, (x, y): (i64, i64), marker: Marker, color: Rgb<u8>) {
        const R: i64 = 5;
        for dy in -R..=R {
            for dx in -R..=R {
                let inside = match marker {
                    Marker::Circle => dx * dx + dy * dy <= R * R,
                    Marker::Square => dx.abs() < R && dy.abs() < R,
                    Marker::Diamond => dx.abs() + dy.abs() <= R + 1,
                    // Apex up, base at the bottom.
                    Marker::Triangle => dy >= -R && 2 * dx.abs() <= dy + R,
                };
                if inside {
                    self.dot(x + dx, y + dy, color);
                }
            }
        }
    }

    fn cross(&mut self, (x, y): (i64, i64), color: Rgb<u8>) {
        self.line((x - 5, y - 5), (x + 5, y + 5), 2, color);
        self.line((x - 5, y + 5), (x + 5, y - 5), 2, color);
    }

    /// Text in the 8x8 font, its top left at `at` (kept inside the image).
    fn text(&mut self, at: (i64, i64), text: &str, color: Rgb<u8>) {
        let at = (at.0.max(0) as u32, at.1.max(0) as u32);
        picture::draw_text(&mut self.0, at, text, 1, color);
    }

    fn text_centered(&mut self, center_x: i64, y: i64, text: &str, color: Rgb<u8>) {
        let width = i64::from(picture::text_width(text, 1));
        self.text((center_x - width / 2, y), text, color);
    }
}

/// `n` with thousands separators.
fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// A decade's label: 0.01, 0.1, 1, 10, ...
fn decade_label(exponent: i32) -> String {
    if exponent >= 0 {
        format!("{}", 10f64.powi(exponent))
    } else {
        format!(
            "{:.*}",
            exponent.unsigned_abs() as usize,
            10f64.powi(exponent)
        )
    }
}

/// The plot: one panel per size, the median time of each (link, mode) against the link's
/// loss rate on a log scale of seconds, with a bar from the fastest to the slowest
/// successful run; the two 20 ms links joined by a line per mode; a cross at the top for
/// a cell whose every run failed. `PANEL.0 * sizes + LEGEND_WIDTH` by `PANEL.1` pixels.
pub(super) fn plot(sizes: &[u64], links: &[Link], modes: &[Mode], cells: &[Cell]) -> RgbImage {
    let width = PANEL.0 * sizes.len() as u32 + LEGEND_WIDTH;
    let mut c = Canvas(RgbImage::from_pixel(width, PANEL.1, WHITE));
    let times: Vec<f64> = cells
        .iter()
        .flat_map(Cell::ok_times)
        .filter(|t| *t > 0.0)
        .collect();
    let (lo, hi) = match Spread::of(&times) {
        Some(Spread { min, max, .. }) => (min.log10().floor() as i32, max.log10().ceil() as i32),
        None => (-2, 1),
    };
    let hi = hi.max(lo + 1);
    let max_loss = links
        .iter()
        .map(|l| l.loss_percent())
        .fold(0.0, f64::max)
        .ceil()
        .max(1.0);
    let (ml, mt, mr, mb) = MARGIN;
    let (pw, ph) = (i64::from(PANEL.0 - ml - mr), i64::from(PANEL.1 - mt - mb));
    for (p, &size) in sizes.iter().enumerate() {
        let x0 = i64::from(PANEL.0) * p as i64 + i64::from(ml);
        let y0 = i64::from(mt);
        let to_x = |loss: f64| x0 + ((loss / max_loss) * (pw - 48) as f64).round() as i64 + 24;
        let to_y = |t: f64| {
            let f = (t.log10() - f64::from(lo)) / f64::from(hi - lo);
            y0 + ph - (f * ph as f64).round() as i64
        };
        c.text_centered(x0 + pw / 2, 12, &format!("{} bytes", grouped(size)), INK);
        c.text((x0 - 64, y0 - 18), "seconds (log)", INK);
        // Grid: decades, with 2 and 5 in between.
        for e in lo..=hi {
            let decade = 10f64.powi(e);
            if e < hi {
                for m in [2.0, 5.0] {
                    let y = to_y(decade * m);
                    c.line((x0, y), (x0 + pw, y), 1, MINOR_GRID);
                }
            }
            let y = to_y(decade);
            c.line((x0, y), (x0 + pw, y), 1, GRID);
            let label = decade_label(e);
            let w = i64::from(picture::text_width(&label, 1));
            c.text((x0 - 8 - w, y - 4), &label, INK);
        }
        let step = if max_loss > 10.0 { 5.0 } else { 1.0 };
        let mut loss = 0.0;
        while loss <= max_loss {
            let x = to_x(loss);
            c.line((x, y0), (x, y0 + ph), 1, MINOR_GRID);
            c.line((x, y0 + ph), (x, y0 + ph + 4), 1, INK);
            c.text_centered(x, y0 + ph + 10, &format!("{loss}"), INK);
            loss += step;
        }
        c.text_centered(x0 + pw / 2, y0 + ph + 30, "loss each way, %", INK);
        // The frame.
        c.line((x0, y0), (x0 + pw, y0), 1, INK);
        c.line((x0, y0 + ph), (x0 + pw, y0 + ph), 1, INK);
        c.line((x0, y0), (x0, y0 + ph), 1, INK);
        c.line((x0 + pw, y0), (x0 + pw, y0 + ph), 1, INK);
        for (mi, &mode) in modes.iter().enumerate() {
            let color = mode.color();
            // Modes side by side at one loss rate, so their bars do not hide each other.
            let shift = (mi as i64 * 2 - (modes.len() as i64 - 1)) * 3;
            let cell = |link: Link| {
                cells
                    .iter()
                    .find(|c| c.link == link && c.size == size && c.mode == mode)
            };
            let mut joined: Vec<(i64, i64)> = links
                .iter()
                .filter(|l| l.on_line())
                .filter_map(|&l| {
                    let median = cell(l)?.stats()?.median;
                    Some((to_x(l.loss_percent()) + shift, to_y(median)))
                })
                .collect();
            joined.sort_unstable();
            for pair in joined.windows(2) {
                c.line(pair[0], pair[1], 2, color);
            }
            for &link in links {
                let Some(cell) = cell(link) else { continue };
                let x = to_x(link.loss_percent()) + shift;
                match cell.stats() {
                    Some(Spread { median, min, max }) => {
                        let (top, bottom) = (to_y(max), to_y(min));
                        c.line((x, top), (x, bottom), 1, color);
                        c.line((x - 3, top), (x + 3, top), 1, color);
                        c.line((x - 3, bottom), (x + 3, bottom), 1, color);
                        c.marker((x, to_y(median)), link.marker(), color);
                    }
                    None if !cell.runs.is_empty() => c.cross((x, y0 + 8), color),
                    None => {}
                }
            }
        }
    }
    // The legend.
    let lx = i64::from(PANEL.0) * sizes.len() as i64 + 10;
    let mut y = i64::from(mt);
    c.text((lx, y), "modes (median,", INK);
    c.text((lx, y + 11), "bar: min-max of ok runs)", INK);
    y += 30;
    for &mode in modes {
        c.line((lx, y + 4), (lx + 22, y + 4), 2, mode.color());
        c.marker((lx + 11, y + 4), Marker::Circle, mode.color());
        c.text((lx + 30, y), mode.name(), INK);
        y += 16;
    }
    y += 12;
    c.text((lx, y), "links", INK);
    y += 16;
    for &link in links {
        c.marker((lx + 11, y + 4), link.marker(), INK);
        c.text((lx + 30, y), link.name(), INK);
        y += 16;
    }
    c.line((lx, y + 4), (lx + 22, y + 4), 2, INK);
    c.text((lx + 30, y), "joins the 20 ms links", INK);
    y += 16;
    c.cross((lx + 11, y + 4), INK);
    c.text((lx + 30, y), "every run failed", INK);
    c.0
}

impl Link {
    fn marker(self) -> Marker {
        match self {
            Self::Loopback => Marker::Square,
            Self::Rtt20 | Self::Rtt20Loss2 => Marker::Circle,
            Self::Rtt20Loss2Rate50 => Marker::Triangle,
            Self::Rtt100Loss5 => Marker::Diamond,
        }
    }
}

impl Mode {
    /// The plot's colour.
    fn color(self) -> Rgb<u8> {
        Rgb(match self {
            Self::StopAndWait => [255, 127, 14],
            Self::Window => [31, 119, 180],
            Self::QBlock => [44, 160, 44],
            Self::Libcoap431 => [214, 39, 40],
            Self::Libcoap435 => [148, 103, 189],
            Self::Quic => [40, 40, 40],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels() {
        assert_eq!(grouped(10_032_012), "10,032,012");
        assert_eq!(grouped(999), "999");
        assert_eq!(decade_label(-2), "0.01");
        assert_eq!(decade_label(0), "1");
        assert_eq!(decade_label(2), "100");
    }
}
