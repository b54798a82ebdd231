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
