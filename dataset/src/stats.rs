//! `labrig dataset stats`: what an index holds (counts by camera bin, object, primitive,
//! format), and a picture: the external cameras' positions seen from above and from the side,
//! coloured by bin, the object positions, and, with a target, the target's cameras and object
//! box with the retrieved episodes drawn over the rest.

use crate::retrieve::{Manifest, Target, Thresholds};
use crate::row::{EXTERNAL_CAMERAS, IndexRow};
use plotters::prelude::*;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Counts of a column's values ("-" for none).
pub fn counts<'a>(rows: &'a [IndexRow], f: impl Fn(&'a IndexRow) -> Vec<Option<&'a str>>) -> BTreeMap<String, usize> {
    let mut out = BTreeMap::new();
    for r in rows {
        for v in f(r) {
            *out.entry(v.unwrap_or("-").to_owned()).or_default() += 1;
        }
    }
    out
}

/// The external cameras' bins, one count per known camera.
pub fn bins(rows: &[IndexRow]) -> BTreeMap<String, usize> {
    counts(rows, |r| {
        EXTERNAL_CAMERAS
            .iter()
            .filter_map(|c| r.camera(c).filter(|c| c.position.is_some()).map(|c| c.bin.as_deref()))
            .collect()
    })
}

fn bin_colour(bin: Option<&str>) -> RGBColor {
    match bin {
        Some("shoulder-left") => RGBColor(31, 119, 180),
        Some("shoulder-right") => RGBColor(255, 127, 14),
        Some("agent-left") => RGBColor(44, 160, 44),
        Some("agent-right") => RGBColor(214, 39, 40),
        Some("agent-front") => RGBColor(148, 103, 189),
        _ => RGBColor(170, 170, 170),
    }
}

/// A drawing error of the PNG backend.
pub type DrawError = DrawingAreaErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>;

/// Why the picture could not be drawn; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StatsError {
    #[error("{}: {source}", path.display())]
    Font {
        path: PathBuf,
        #[source]
        source: labrig_episode::font::FontError,
    },
    #[error("{}: {source:?}", path.display())]
    Draw {
        path: PathBuf,
        #[source]
        source: DrawError,
    },
}

/// Draws the two views into `path` (PNG). `retrieved`: the manifest of a retrieval, whose
/// episodes are drawn on top, with its target.
pub fn plot(rows: &[IndexRow], retrieved: Option<&Manifest>, path: &Path) -> Result<(), StatsError> {
    let font =
        labrig_episode::font::dejavu_sans().map_err(|source| StatsError::Font { path: path.to_owned(), source })?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let picked: BTreeSet<&str> =
        retrieved.map(|m| m.episodes.iter().map(|e| e.path.as_str()).collect()).unwrap_or_default();
    let root = BitMapBackend::new(path, (1400, 700)).into_drawing_area();
    let e = |source: DrawError| StatsError::Draw { path: path.to_owned(), source };
    root.fill(&WHITE).map_err(e)?;
    let (top, side) = root.split_horizontally(700);
    // (x, y) from above and (x, z) from the side, base frame.
    for (area, vertical, name) in [(&top, 1usize, "from above: y (m)"), (&side, 2, "from the side: z (m)")] {
        let yr = if vertical == 1 { -1.5..1.5 } else { -0.2..1.6 };
        let mut chart = ChartBuilder::on(area)
            .caption(
                if vertical == 1 { "cameras (by bin) and objects, seen from above" } else { "seen from the side" },
                ("sans-serif", 20),
            )
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(50)
            .build_cartesian_2d(-0.8f64..1.8, yr)
            .map_err(e)?;
        chart.configure_mesh().x_desc("x (m)").y_desc(name).draw().map_err(e)?;
        let mut cams = Vec::new();
        let mut objects = Vec::new();
        for r in rows {
            let on = picked.contains(r.source_path.as_str());
            for c in EXTERNAL_CAMERAS {
                if let Some(cam) = r.camera(c)
                    && let Some(p) = cam.position
                {
                    cams.push((p[0], p[vertical], bin_colour(cam.bin.as_deref()), on));
                }
            }
            if let Some(p) = r.object_position {
                objects.push((p[0], p[vertical], on));
            }
        }
        // The rest faint, the retrieved on top.
        let faint = !picked.is_empty();
        chart
            .draw_series(
                cams.iter()
                    .filter(|c| !c.3)
                    .map(|(x, y, col, _)| Circle::new((*x, *y), 3, col.mix(if faint { 0.25 } else { 0.8 }).filled())),
            )
            .map_err(e)?;
        chart
            .draw_series(
                objects
                    .iter()
                    .filter(|o| !o.2)
                    .map(|(x, y, _)| Cross::new((*x, *y), 3, BLACK.mix(if faint { 0.2 } else { 0.6 }).stroke_width(1))),
            )
            .map_err(e)?;
        chart
            .draw_series(cams.iter().filter(|c| c.3).map(|(x, y, col, _)| Circle::new((*x, *y), 5, col.filled())))
            .map_err(e)?;
        chart
            .draw_series(objects.iter().filter(|o| o.2).map(|(x, y, _)| Cross::new((*x, *y), 5, BLACK.stroke_width(2))))
            .map_err(e)?;
        // The robot base and the table centre.
        chart.draw_series([TriangleMarker::new((0.0, 0.0), 8, BLACK.filled())]).map_err(e)?;
        if let Some(m) = retrieved {
            draw_target(&mut chart, &m.target, &m.thresholds, vertical).map_err(e)?;
        }
        if vertical == 1 {
            for (k, bin) in labrig_msgs::dv::CameraBin::ALL.iter().enumerate() {
                let y = 1.4 - 0.12 * k as f64;
                chart.draw_series([Circle::new((1.15, y), 5, bin_colour(Some(bin.name())).filled())]).map_err(e)?;
                chart
                    .draw_series([Text::new(bin.name().to_owned(), (1.22, y + 0.04), ("sans-serif", 14))])
                    .map_err(e)?;
            }
        }
    }
    root.present().map_err(e)?;
    Ok(())
}

type Chart<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

fn draw_target<'b>(
    chart: &mut Chart<'_, 'b>,
    t: &Target,
    th: &Thresholds,
    vertical: usize,
) -> Result<(), DrawingAreaErrorKind<<BitMapBackend<'b> as DrawingBackend>::ErrorType>> {
    let blue = RGBColor(0, 90, 200);
    let (hx, hv) = (th.cam_xy_m, if vertical == 1 { th.cam_xy_m } else { th.cam_z_m });
    for c in &t.cameras {
        chart.draw_series([Rectangle::new(
            [(c[0] - hx, c[vertical] - hv), (c[0] + hx, c[vertical] + hv)],
            blue.stroke_width(2),
        )])?;
        chart.draw_series([Circle::new((c[0], c[vertical]), 6, blue.filled())])?;
    }
    if let Some(o) = t.object_position {
        let (bx, bv) = (th.obj_box_m[0] / 2.0, th.obj_box_m[vertical] / 2.0);
        chart.draw_series([Rectangle::new(
            [(o[0] - bx, o[vertical] - bv), (o[0] + bx, o[vertical] + bv)],
            blue.stroke_width(1),
        )])?;
    }
    Ok(())
}
