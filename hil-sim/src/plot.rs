//! PNG figures in the style of the paper: the hysteresis loop (Fig. 11) and each model's estimate
//! and error profile along a scenario (Figs. 19-24).

use std::path::Path;

use plotters::prelude::*;

use crate::run::Trace;

/// Where the report looks for a TrueType font (Debian's fonts-dejavu-core).
pub const FONT_PATHS: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
];

/// Registers a font for plot text once; Err says which files were tried.
pub fn init_fonts() -> Result<(), crate::error::Error> {
    use crate::error::Error;
    // The outcome of the one registration, for every later call (an `Error` is not `Clone`).
    static DONE: std::sync::OnceLock<Result<(), Option<&'static str>>> = std::sync::OnceLock::new();
    let done = DONE.get_or_init(|| {
        for p in FONT_PATHS {
            if let Ok(bytes) = std::fs::read(p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                return plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                    .map_err(|_| Some(*p));
            }
        }
        Err(None)
    });
    match *done {
        Ok(()) => Ok(()),
        Err(Some(p)) => Err(Error::BadFont(p.to_string())),
        Err(None) => Err(Error::NoFont(FONT_PATHS.join(", "))),
    }
}

type PlotResult = Result<(), Box<dyn std::error::Error>>;

fn range(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
        (l.min(v), h.max(v))
    });
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return (lo - 1.0, lo + 1.0);
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// Keeps at most `n` evenly spaced points of a long series (plots need no 400k points).
fn thin(len: usize, n: usize) -> impl Iterator<Item = usize> {
    let step = len.div_ceil(n.max(1)).max(1);
    (0..len).step_by(step)
}

/// Fig. 11: Delta x = x_LS - x_PE against x_PE, every trace overlaid.
pub fn hysteresis(path: &Path, title: &str, traces: &[Trace]) -> PlotResult {
    init_fonts()?;
    let root = BitMapBackend::new(path, (1000, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let xs = range(
        traces
            .iter()
            .flat_map(|t| (0..t.records.len()).map(move |i| t.x_pe_mm(i))),
    );
    let ys = range(
        traces
            .iter()
            .flat_map(|t| (0..t.records.len()).map(move |i| t.dx_um(i))),
    );
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(xs.0..xs.1, ys.0..ys.1)?;
    chart
        .configure_mesh()
        .x_desc("x_PE (mm)")
        .y_desc("x_LS - x_PE (um)")
        .draw()?;
    for (k, t) in traces.iter().enumerate() {
        let color = Palette99::pick(k).mix(0.8);
        chart.draw_series(LineSeries::new(
            thin(t.records.len(), 20_000).map(|i| (t.x_pe_mm(i), t.dx_um(i))),
            color.stroke_width(1),
        ))?;
    }
    root.present()?;
    Ok(())
}

/// The value ranges every estimate figure of one scenario shares, so that the models and the
/// baselines compare at a glance: (measured and estimate, um), (error e, um).
pub fn estimate_scales(trace: &Trace, estimates: &[&[f64]]) -> ((f64, f64), (f64, f64)) {
    let n = trace.records.len();
    let values = range(
        (0..n)
            .map(|i| trace.dx_um(i))
            .chain(estimates.iter().flat_map(|y| y.iter().copied())),
    );
    let errors = range(
        estimates
            .iter()
            .flat_map(|y| (0..n.min(y.len())).map(move |i| trace.dx_um(i) - y[i])),
    );
    (values, errors)
}

/// Figs. 19-24: measured Delta x and the model's estimate y against time (top), and the
/// estimation error e = Delta x - y (bottom), on the scales of [`estimate_scales`].
pub fn estimate(
    path: &Path,
    title: &str,
    trace: &Trace,
    y_um: &[f64],
    scales: ((f64, f64), (f64, f64)),
) -> PlotResult {
    init_fonts()?;
    let root = BitMapBackend::new(path, (1000, 700)).into_drawing_area();
    root.fill(&WHITE)?;
    let (top, bottom) = root.split_vertically(420);
    let n = trace.records.len().min(y_um.len());
    let t_end = trace.records.last().map_or(1.0, |r| r.t_s);
    let (ys, es) = scales;
    let mut c = ChartBuilder::on(&top)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(30)
        .y_label_area_size(60)
        // Headroom above the data for the legend, so that it never covers a curve.
        .build_cartesian_2d(0.0..t_end, ys.0..ys.1 + 0.3 * (ys.1 - ys.0))?;
    c.configure_mesh().y_desc("um").draw()?;
    c.draw_series(LineSeries::new(
        thin(n, 20_000).map(|i| (trace.records[i].t_s, trace.dx_um(i))),
        BLUE.stroke_width(1),
    ))?
    .label("measured x_LS - x_PE")
    .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLUE));
    c.draw_series(LineSeries::new(
        thin(n, 20_000).map(|i| (trace.records[i].t_s, y_um[i])),
        RED.stroke_width(1),
    ))?
    .label("estimate y")
    .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], RED));
    c.configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;

    let mut c = ChartBuilder::on(&bottom)
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, es.0..es.1)?;
    c.configure_mesh()
        .x_desc("time (s)")
        .y_desc("error e (um)")
        .draw()?;
    c.draw_series(LineSeries::new([(0.0, 0.0), (t_end, 0.0)], BLACK.mix(0.3)))?;
    c.draw_series(LineSeries::new(
        thin(n, 20_000).map(|i| (trace.records[i].t_s, trace.dx_um(i) - y_um[i])),
        BLACK.stroke_width(1),
    ))?;
    root.present()?;
    Ok(())
}

/// The scenario itself (as the paper's Fig. 18): motor position against time.
pub fn scenario(path: &Path, title: &str, trace: &Trace) -> PlotResult {
    init_fonts()?;
    let root = BitMapBackend::new(path, (1000, 400)).into_drawing_area();
    root.fill(&WHITE)?;
    let n = trace.records.len();
    let t_end = trace.records.last().map_or(1.0, |r| r.t_s);
    let xs = range((0..n).map(|i| trace.x_pe_mm(i)));
    let mut c = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, xs.0..xs.1)?;
    c.configure_mesh()
        .x_desc("time (s)")
        .y_desc("x_PE (mm)")
        .draw()?;
    c.draw_series(LineSeries::new(
        thin(n, 20_000).map(|i| (trace.records[i].t_s, trace.x_pe_mm(i))),
        BLUE.stroke_width(2),
    ))?;
    root.present()?;
    Ok(())
}

/// Carriage placement: the arrival error of every move (scale at rest minus the target) per
/// compensator, one shared scale so that their sizes compare at a glance.
pub fn arrivals(path: &Path, title: &str, series: &[(&str, Vec<(usize, f64)>)]) -> PlotResult {
    init_fonts()?;
    let root = BitMapBackend::new(path, (1000, 500)).into_drawing_area();
    root.fill(&WHITE)?;
    let last = series
        .iter()
        .flat_map(|(_, v)| v.iter().map(|p| p.0))
        .max()
        .unwrap_or(0) as f64;
    let ys = range(
        series
            .iter()
            .flat_map(|(_, v)| v.iter().map(|p| p.1))
            .chain([0.0]),
    );
    let mut c = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        // Headroom above the data for the legend.
        .build_cartesian_2d(-0.5..last + 0.5, ys.0..ys.1 + 0.35 * (ys.1 - ys.0))?;
    c.configure_mesh()
        .x_desc("move")
        .y_desc("arrival error (um)")
        .draw()?;
    c.draw_series(LineSeries::new(
        [(-0.5, 0.0), (last + 0.5, 0.0)],
        BLACK.mix(0.4),
    ))?;
    for (k, (name, pts)) in series.iter().enumerate() {
        const COLORS: [RGBColor; 4] = [
            RGBColor(200, 30, 30),
            RGBColor(230, 140, 0),
            RGBColor(20, 80, 200),
            RGBColor(40, 150, 60),
        ];
        let color = COLORS[k % COLORS.len()];
        let rms = (pts.iter().map(|p| p.1 * p.1).sum::<f64>() / pts.len().max(1) as f64).sqrt();
        c.draw_series(
            pts.iter()
                .map(|&(i, e)| Circle::new((i as f64, e), 4, color.filled())),
        )?
        .label(format!("{name} (RMS {rms:.1} um)"))
        .legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
        c.draw_series(LineSeries::new(
            pts.iter().map(|&(i, e)| (i as f64, e)),
            color.mix(0.5).stroke_width(1),
        ))?;
    }
    c.configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}

/// The calibration's region of motion: a grey square per half-octave cell of (peak speed,
/// acceleration) its moves reached, darker with more moves; a run's moves on top, blue inside
/// and red outside (no calibration move within a factor of two in both).
pub fn coverage(
    path: &Path,
    title: &str,
    region: &crate::coverage::Coverage,
    run: &crate::coverage::Check,
) -> PlotResult {
    use crate::coverage::{band, band_floor, Outside};
    init_fonts()?;
    let moves = &run.extents;
    let root = BitMapBackend::new(path, (900, 700)).into_drawing_area();
    root.fill(&WHITE)?;
    let cells = region.cells.keys();
    let mut s_bands = cells
        .clone()
        .map(|c| c.0)
        .chain(moves.iter().map(|(_, m)| band(m.peak_mm_s)));
    let mut a_bands = cells
        .map(|c| c.1)
        .chain(moves.iter().map(|(_, m)| band(m.accel_mm_s2)));
    let span = |b: &mut dyn Iterator<Item = i32>| {
        let (lo, hi) = b.fold((i32::MAX, i32::MIN), |(l, h), k| (l.min(k), h.max(k)));
        if lo > hi {
            (1.0, 10.0)
        } else {
            (band_floor(lo - 1), band_floor(hi + 2))
        }
    };
    let (s_lo, s_hi) = span(&mut s_bands);
    let (a_lo, a_hi) = span(&mut a_bands);
    let mut c = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((s_lo..s_hi).log_scale(), (a_lo..a_hi).log_scale())?;
    c.configure_mesh()
        .x_desc("peak speed (mm/s)")
        .y_desc("acceleration (mm/s²)")
        .x_label_formatter(&|v| crate::coverage::fmt_value(*v))
        .y_label_formatter(&|v| crate::coverage::fmt_value(*v))
        .light_line_style(WHITE)
        .draw()?;
    let most = region.cells.values().copied().max().unwrap_or(1).max(1) as f64;
    c.draw_series(region.cells.iter().map(|(&(s, a), &n)| {
        let shade = 0.25 + 0.6 * (n as f64).ln_1p() / most.ln_1p();
        Rectangle::new(
            [
                (band_floor(s), band_floor(a)),
                (band_floor(s + 1), band_floor(a + 1)),
            ],
            BLACK.mix(shade).filled(),
        )
    }))?
    .label("calibration moves (darker: more)")
    .legend(|(x, y)| Rectangle::new([(x + 4, y - 5), (x + 14, y + 5)], BLACK.mix(0.5).filled()));
    let out: std::collections::BTreeSet<usize> = run
        .outside
        .iter()
        .filter_map(|o| match o {
            Outside::SpeedAccel { index, .. } => Some(*index),
            Outside::Travel { .. } => None,
        })
        .collect();
    let (inside_pts, outside_pts): (Vec<_>, Vec<_>) =
        moves.iter().partition(|(i, _)| !out.contains(i));
    let blue = RGBColor(20, 80, 200);
    let red = RGBColor(200, 30, 30);
    c.draw_series(
        inside_pts
            .iter()
            .map(|(_, m)| Circle::new((m.peak_mm_s, m.accel_mm_s2), 4, blue.filled())),
    )?
    .label(format!("{}: inside", run.scenario))
    .legend(move |(x, y)| Circle::new((x + 10, y), 4, blue.filled()));
    c.draw_series(
        outside_pts
            .iter()
            .map(|(_, m)| Cross::new((m.peak_mm_s, m.accel_mm_s2), 6, red.stroke_width(2))),
    )?
    .label(format!("{}: outside", run.scenario))
    .legend(move |(x, y)| Cross::new((x + 10, y), 6, red.stroke_width(2)));
    c.configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}

/// Model 4's colour where it is the best estimator of a row, and where it is not.
pub const GENERALISATION_BEST: RGBColor = RGBColor(40, 150, 60);
/// See [`GENERALISATION_BEST`].
pub const GENERALISATION_LOST: RGBColor = RGBColor(210, 30, 30);
const GENERALISATION_OTHER: RGBColor = RGBColor(230, 140, 0);

/// Size of [`generalisation`]'s picture for `plants` panels, pixels.
pub fn generalisation_size(plants: usize) -> (u32, u32) {
    (1200, 60 + 280 * plants.max(1) as u32)
}

/// The generalisation tables as a picture, one panel per plant, RMS of e on a log scale per
/// workload: the band from the floor to 4x the floor, no model, the best other estimator, and
/// Model 4, green where it is the best of the row and red where it is not.
pub fn generalisation(path: &Path, tables: &[crate::generalise::PlantTable]) -> PlotResult {
    init_fonts()?;
    let root = BitMapBackend::new(path, generalisation_size(tables.len())).into_drawing_area();
    generalisation_on(&root, tables)?;
    root.present()?;
    Ok(())
}

/// [`generalisation`] on any drawing area (tests draw into a buffer and read the pixels).
pub fn generalisation_on<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    tables: &[crate::generalise::PlantTable],
) -> PlotResult
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)?;
    let (legend, body) = root.split_vertically(60);
    // One scale for every panel, so that plants compare at a glance.
    let values = tables.iter().flat_map(|t| {
        t.rows
            .iter()
            .flat_map(|r| r.rms_um.iter().map(|x| x.1).chain([r.floor_um]))
    });
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, 0.0_f64), |(l, h), v| (l.min(v), h.max(v)));
    let (lo, hi) = if lo < hi {
        (lo / 1.5, hi * 1.5)
    } else {
        (0.1, 1000.0)
    };
    let font = ("sans-serif", 15).into_font();
    // The legend, once, above the panels.
    let items: [(&str, RGBColor); 5] = [
        ("floor to 4x floor", RGBColor(150, 150, 150)),
        ("no model", RGBColor(120, 120, 120)),
        ("best other estimator", GENERALISATION_OTHER),
        ("Model 4, best of the row", GENERALISATION_BEST),
        ("Model 4, not the best", GENERALISATION_LOST),
    ];
    legend.draw_text(
        "Generalisation: RMS of e per held-out workload (um, log scale)",
        &("sans-serif", 20).into_font().color(&BLACK),
        (12, 6),
    )?;
    let mut x = 14;
    for (k, (name, color)) in items.iter().enumerate() {
        let at = (x + 6, 44);
        match k {
            0 => legend.draw(&Rectangle::new(
                [(x, 37), (x + 12, 51)],
                color.mix(0.35).filled(),
            ))?,
            1 => legend.draw(&Cross::new(at, 5, color.stroke_width(2)))?,
            2 => legend.draw(&TriangleMarker::new(at, 6, color.filled()))?,
            _ => legend.draw(&Circle::new(at, 5, color.filled()))?,
        }
        legend.draw_text(name, &font.color(&BLACK), (x + 18, 36))?;
        x += 30 + 8 * name.len() as i32;
    }
    if tables.is_empty() {
        return Ok(());
    }
    for (t, area) in tables.iter().zip(body.split_evenly((tables.len(), 1))) {
        let n = t.rows.len();
        let mut c = ChartBuilder::on(&area)
            .caption(&t.plant, ("sans-serif", 17))
            .margin(8)
            .x_label_area_size(44)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.5..n as f64 - 0.5, (lo..hi).log_scale())?;
        c.configure_mesh()
            .disable_x_mesh()
            .x_labels(0)
            .y_desc("um")
            .draw()?;
        // A value that is not a positive number has no place on a log scale: left out.
        let shown = |v: f64| (v.is_finite() && v > 0.0).then_some(v);
        let band = RGBColor(150, 150, 150);
        c.draw_series(
            t.rows
                .iter()
                .enumerate()
                .filter(|(_, r)| shown(r.floor_um).is_some())
                .map(|(i, r)| {
                    let i = i as f64;
                    Rectangle::new(
                        [(i - 0.3, r.floor_um), (i + 0.3, 4.0 * r.floor_um)],
                        band.mix(0.35).filled(),
                    )
                }),
        )?;
        c.draw_series(t.rows.iter().enumerate().filter_map(|(i, r)| {
            let v = shown(r.rms("none")?)?;
            Some(Cross::new(
                (i as f64, v),
                5,
                RGBColor(120, 120, 120).stroke_width(2),
            ))
        }))?;
        c.draw_series(t.rows.iter().enumerate().filter_map(|(i, r)| {
            // The lowest estimator other than none and Model 4, left of Model 4 so that neither
            // hides the other where they are close.
            let v = r
                .rms_um
                .iter()
                .filter(|(k, _)| *k != "none" && *k != "model4")
                .filter_map(|x| shown(x.1))
                .min_by(f64::total_cmp)?;
            Some(TriangleMarker::new(
                (i as f64 - 0.13, v),
                6,
                GENERALISATION_OTHER.filled(),
            ))
        }))?;
        c.draw_series(t.rows.iter().enumerate().filter_map(|(i, r)| {
            let v = shown(r.rms("model4")?)?;
            let color = if r.best() == "model4" {
                GENERALISATION_BEST
            } else {
                GENERALISATION_LOST
            };
            Some(Circle::new((i as f64 + 0.13, v), 5, color.filled()))
        }))?;
        // Workload names under the panel, staggered on two lines so that long ones fit.
        for (i, r) in t.rows.iter().enumerate() {
            let (px, py) = c.backend_coord(&(i as f64, lo));
            let (ax, ay) = area.get_base_pixel();
            let name = short_workload(&r.workload);
            let w = 7 * name.len() as i32;
            area.draw_text(
                &name,
                &("sans-serif", 13).into_font().color(&BLACK),
                (px - ax - w / 2, py - ay + 6 + 16 * (i % 2) as i32),
            )?;
        }
    }
    Ok(())
}

/// A generated workload's name without its seed (`printer-raster-11` -> `printer-raster`).
fn short_workload(name: &str) -> String {
    match name.rsplit_once('-') {
        Some((head, seed)) if !seed.is_empty() && seed.bytes().all(|b| b.is_ascii_digit()) => {
            head.to_string()
        }
        _ => name.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generalise::{PlantTable, Row};

    fn row(name: &str, model4: f64, model3: f64) -> Row {
        Row {
            workload: name.into(),
            floor_um: 1.5,
            rms_um: vec![("none", 200.0), ("model3", model3), ("model4", model4)],
            moves: 4,
            moves_outside: 0,
        }
    }

    /// Pixels of exactly `color` below the legend, in a picture of `tables`.
    fn pixels_of(tables: &[PlantTable], color: RGBColor) -> Option<usize> {
        init_fonts().ok()?;
        let (w, h) = generalisation_size(tables.len());
        let mut buf = vec![0u8; (w * h * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            generalisation_on(&root, tables).expect("drawn");
            root.present().expect("presented");
        }
        let body = &buf[(60 * w * 3) as usize..];
        Some(
            body.chunks(3)
                .filter(|p| p == &[color.0, color.1, color.2])
                .count(),
        )
    }

    /// Model 4 is drawn red on the rows it loses and only there; the plot survives a table with
    /// no rows and a value that is not a number.
    #[test]
    fn model4_is_red_where_it_loses() {
        let table = |rows| PlantTable {
            plant: "a plant".into(),
            fit_rms_um: vec![],
            rows,
        };
        let won = [table(vec![
            row("fig18", 10.0, 20.0),
            row("raster-11", 30.0, 40.0),
        ])];
        let lost = [table(vec![
            row("fig18", 10.0, 20.0),
            row("raster-11", 50.0, 40.0),
        ])];
        let (Some(red_won), Some(red_lost), Some(green_won), Some(green_lost)) = (
            pixels_of(&won, GENERALISATION_LOST),
            pixels_of(&lost, GENERALISATION_LOST),
            pixels_of(&won, GENERALISATION_BEST),
            pixels_of(&lost, GENERALISATION_BEST),
        ) else {
            // No font here: `hil-sim report` says so by name (tests/coverage.rs).
            assert!(init_fonts().is_err());
            return;
        };
        // Two rows won: two green points. One lost: one green and one red point, each the
        // size of the others (coloured row by row, not plant by plant).
        assert_eq!(red_won, 0);
        assert!(green_won > 40, "{green_won}");
        assert_eq!(2 * green_lost, green_won);
        assert_eq!(red_lost, green_lost);
        let odd = [table(vec![]), table(vec![row("nan", f64::NAN, 20.0)])];
        assert!(pixels_of(&odd, GENERALISATION_BEST).is_some());
        assert!(pixels_of(&[], GENERALISATION_BEST).is_some());
    }

    #[test]
    fn workload_names_lose_their_seed_only() {
        assert_eq!(short_workload("printer-raster-11"), "printer-raster");
        assert_eq!(short_workload("fig18"), "fig18");
        assert_eq!(
            short_workload("high-accel-reversals"),
            "high-accel-reversals"
        );
        assert_eq!(short_workload("x-"), "x-");
    }
}
