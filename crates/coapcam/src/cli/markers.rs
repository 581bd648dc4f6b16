//! `coapcam markers`: a PDF of AprilTag markers to print and lay on the table for
//! `calibrate`, at their true size (`markers::sheet`).

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Args;
use markers::Family;
use markers::sheet::{Paper, Sheet, SheetError};

use super::{Exit, usage, values};

/// Flags of `markers`.
#[derive(Debug, Args)]
pub(crate) struct MarkersArgs {
    /// The marker family (calibrate's --family).
    #[arg(long, value_name = "F", default_value = "tag36h11", value_parser = clap::value_parser!(Family))]
    family: Family,
    /// The markers' ids: numbers and ranges, e.g. 0-3 or 0,2,5-7. Marker 0 is the
    /// origin of calibrate's frame (its --origin-id).
    #[arg(long, value_name = "LIST", default_value = "0-3", value_parser = parse_ids)]
    ids: Ids,
    /// The side of each marker's black square, metres (calibrate's --marker-size, or the
    /// `size` of a --map's markers). Each marker also has a white border one cell wide
    /// (a quarter of the side, on both sides together) that must stay clear. 0.16 fills an
    /// A4 page; smaller markers share pages.
    #[arg(long, value_name = "M", default_value = "0.16", value_parser = values::marker_metres)]
    size: f64,
    /// The paper: a4 or letter.
    #[arg(long, value_name = "PAPER", default_value = "a4", value_parser = clap::value_parser!(Paper))]
    paper: Paper,
    /// The PDF file to write. Print it at 100 % ("actual size", not "fit to page") and
    /// check the 100 mm bar on each page with a ruler.
    #[arg(short = 'o', long = "output", value_name = "FILE.pdf")]
    output: PathBuf,
    /// Also write where the markers lie on the page, as the `[[marker]]` tables of
    /// calibrate's --map (metres from the first marker's centre; the markers must fit on
    /// one page). Laid flat, one printed page then calibrates every camera that sees any
    /// of its markers, with no measuring by hand.
    #[arg(long, value_name = "FILE.toml")]
    map: Option<PathBuf>,
}

/// Marker ids, in the order given.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Ids(Vec<u32>);

/// `0-3`, `0,2,5-7`: the ids in the order given.
fn parse_ids(text: &str) -> Result<Ids, String> {
    let number = |t: &str| {
        t.trim()
            .parse::<u32>()
            .map_err(|_| format!("{t:?} is not a marker id (0, 1, ...)"))
    };
    let mut ids = Vec::new();
    for part in text.split(',') {
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (number(a)?, number(b)?);
                if a > b {
                    return Err(format!("{part}: the range runs backwards"));
                }
                if b - a >= 10_000 {
                    return Err(format!("{part}: more markers than any family has"));
                }
                ids.extend(a..=b);
            }
            None => ids.push(number(part)?),
        }
    }
    Ok(Ids(ids))
}

/// Runs `markers`.
pub(crate) async fn run(args: MarkersArgs) -> anyhow::Result<Exit> {
    if !args
        .output
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("pdf"))
    {
        usage!(
            "-o {}: the sheet is a PDF; give a file name ending in .pdf",
            args.output.display()
        );
    }
    let sheet = match Sheet::layout(args.family, &args.ids.0, args.size, args.paper) {
        Ok(sheet) => sheet,
        Err(e @ (SheetError::Id { .. } | SheetError::Size { .. } | SheetError::NoIds)) => {
            usage!("{e}")
        }
        Err(e) => return Err(e.into()),
    };
    let map = match (&args.map, sheet.map()) {
        (None, _) => None,
        (Some(path), Some(map)) => Some((path, map_toml(&sheet, &map, &args))),
        (Some(_), None) => usage!(
            "--map needs the markers on one page; these take {} (fewer or smaller markers, or lay them out by hand: docs/markers.md)",
            sheet.pages.len()
        ),
    };
    std::fs::write(&args.output, sheet.pdf())
        .with_context(|| format!("writing {}", args.output.display()))?;
    if let Some((path, text)) = map {
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
        eprintln!(
            "coapcam: wrote {}: the map of the page for calibrate --map",
            path.display()
        );
    }
    let per_page = sheet.pages.first().map_or(0, Vec::len);
    eprintln!(
        "coapcam: wrote {}: {} {} marker(s) on {} page(s) ({per_page} a page), black squares {} mm; print at 100 % and check the 100 mm bar",
        args.output.display(),
        args.ids.0.len(),
        args.family,
        sheet.pages.len(),
        sheet.size_mm
    );
    Ok(Exit::Success)
}

/// The map of a one-page sheet as calibrate's `--map` reads it.
fn map_toml(sheet: &Sheet, map: &[(u32, [f64; 2])], args: &MarkersArgs) -> String {
    let mut out = format!(
        "# The markers of {} as printed on one page, laid flat: metres from marker {}'s\n\
         # centre, x to the right and y up the page. For coapcam calibrate --map.\n",
        args.output.display(),
        map.first().map_or(0, |m| m.0)
    );
    for (id, [x, y]) in map {
        out += &format!(
            "\n[[marker]]\nfamily = \"{}\"\nid = {id}\nsize = {}\ncenter = [{x:.6}, {y:.6}]\nyaw_deg = 0.0\n",
            sheet.family,
            sheet.size_mm / 1000.0
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_numbers_and_ranges() {
        assert_eq!(parse_ids("0-3"), Ok(Ids(vec![0, 1, 2, 3])));
        assert_eq!(parse_ids("5,0-1"), Ok(Ids(vec![5, 0, 1])));
        for bad in ["3-1", "x", "", "1-", "-1"] {
            assert!(parse_ids(bad).is_err(), "{bad}");
        }
    }
}
