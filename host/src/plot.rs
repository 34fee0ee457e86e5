//! An SVG picture of a time window of a run: toolhead velocity from the
//! planned moves, and each stepper's step rate from its steps.

use onechip_planner::move_sink::TrapqMove;
use std::fmt::Write as _;

/// Width and height of one chart, px.
const WIDTH: f64 = 900.0;
const HEIGHT: f64 = 220.0;
/// Margins around a chart for labels, px.
const LEFT: f64 = 70.0;
const TOP: f64 = 30.0;
/// Step rate bins per window.
const BINS: usize = 300;
/// Colours of the stepper lines, in stepper order.
const COLOURS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
];

/// One line of a chart: name, colour, points (time s, value).
struct Series<'n> {
    name: &'n str,
    colour: &'static str,
    points: Vec<(f64, f64)>,
}

/// A time window of print time, s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Start, s.
    pub from: f64,
    /// End, s (after `from`).
    pub to: f64,
}

/// Toolhead speed along `m` at `t` s into it, mm/s.
fn speed(m: &TrapqMove, t: f64) -> f64 {
    if t < m.accel_t {
        m.start_v + m.accel * t
    } else if t < m.accel_t + m.cruise_t {
        m.cruise_v
    } else {
        m.cruise_v - m.accel * (t - m.accel_t - m.cruise_t)
    }
}

/// Velocity samples (time s, mm/s) of `moves` within `window`: the phase
/// boundaries of each move (speed is linear between them), and rest
/// between moves.
fn velocity(moves: &[TrapqMove], window: Window) -> Vec<(f64, f64)> {
    let mut points = vec![(window.from, 0.0)];
    for m in moves {
        let end = m.print_time + m.accel_t + m.cruise_t + m.decel_t;
        if end < window.from || m.print_time > window.to {
            continue;
        }
        for t in [0.0, m.accel_t, m.accel_t + m.cruise_t, end - m.print_time] {
            let at = m.print_time + t;
            if (window.from..=window.to).contains(&at) {
                points.push((at, speed(m, t.min(end - m.print_time))));
            }
        }
    }
    points.push((window.to, 0.0));
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    points
}

/// Steps per second of `steps` (print times, s) in [`BINS`] bins.
fn rate(steps: &[f64], window: Window) -> Vec<(f64, f64)> {
    let width = (window.to - window.from) / BINS as f64;
    let mut counts = [0u32; BINS];
    for &t in steps {
        if (window.from..window.to).contains(&t) {
            let bin = (((t - window.from) / width) as usize).min(BINS - 1);
            counts[bin] += 1;
        }
    }
    counts
        .iter()
        .enumerate()
        .map(|(i, &n)| (window.from + (i as f64 + 0.5) * width, f64::from(n) / width))
        .collect()
}

/// One chart: a frame, labels and the series, at vertical offset `y0`.
fn chart(
    out: &mut String,
    y0: f64,
    title: &str,
    unit: &str,
    window: Window,
    series: &[Series<'_>],
) {
    let top = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .fold(1.0, f64::max)
        * 1.05;
    let x = |t: f64| LEFT + (t - window.from) / (window.to - window.from) * WIDTH;
    let y = |v: f64| y0 + TOP + HEIGHT - v / top * HEIGHT;
    let _ = writeln!(
        out,
        r##"<rect x="{LEFT}" y="{}" width="{WIDTH}" height="{HEIGHT}" fill="none" stroke="#888"/>"##,
        y0 + TOP
    );
    let _ = writeln!(
        out,
        r#"<text x="{LEFT}" y="{}" font-size="14">{title}</text>"#,
        y0 + TOP - 8.0
    );
    for k in 0..=4 {
        let v = top * f64::from(k) / 4.0;
        let _ = writeln!(
            out,
            r#"<text x="{}" y="{:.1}" font-size="11" text-anchor="end">{v:.0} {unit}</text>"#,
            LEFT - 4.0,
            y(v) + 4.0
        );
        let t = window.from + (window.to - window.from) * f64::from(k) / 4.0;
        let _ = writeln!(
            out,
            r#"<text x="{:.1}" y="{}" font-size="11" text-anchor="middle">{t:.3} s</text>"#,
            x(t),
            y0 + TOP + HEIGHT + 14.0
        );
    }
    for (i, line) in series.iter().enumerate() {
        let (name, colour) = (line.name, line.colour);
        let path: Vec<String> = line
            .points
            .iter()
            .map(|&(t, v)| format!("{:.1},{:.1}", x(t), y(v)))
            .collect();
        let _ = writeln!(
            out,
            r#"<polyline fill="none" stroke="{colour}" stroke-width="1.2" points="{}"/>"#,
            path.join(" ")
        );
        let _ = writeln!(
            out,
            r#"<text x="{}" y="{}" font-size="12" fill="{colour}">{name}</text>"#,
            LEFT + WIDTH - 160.0,
            y0 + TOP + 16.0 + 14.0 * i as f64
        );
    }
}

/// The SVG: toolhead velocity (from `moves`) over `window`, then the step
/// rate of each `(name, step times in s)`.
pub fn svg(moves: &[TrapqMove], steppers: &[(&str, Vec<f64>)], window: Window) -> String {
    let mut out = String::new();
    let total_height = 2.0 * (HEIGHT + TOP + 30.0);
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{}" height="{total_height}" font-family="sans-serif">"#,
        WIDTH + LEFT + 20.0
    );
    chart(
        &mut out,
        0.0,
        "toolhead velocity",
        "mm/s",
        window,
        &[Series {
            name: "velocity",
            colour: "#000",
            points: velocity(moves, window),
        }],
    );
    let series: Vec<Series<'_>> = steppers
        .iter()
        .enumerate()
        .map(|(i, (name, steps))| Series {
            name,
            colour: COLOURS[i % COLOURS.len()],
            points: rate(steps, window),
        })
        .collect();
    chart(
        &mut out,
        HEIGHT + TOP + 30.0,
        "step rate",
        "steps/s",
        window,
        &series,
    );
    out.push_str("</svg>\n");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trapezoid() -> TrapqMove {
        TrapqMove {
            print_time: 1.0,
            accel_t: 0.1,
            cruise_t: 0.2,
            decel_t: 0.1,
            start_pos: [0.0; 3],
            axes_r: [1.0, 0.0, 0.0],
            start_v: 0.0,
            cruise_v: 100.0,
            accel: 1000.0,
        }
    }

    #[test]
    fn velocity_follows_the_trapezoid() {
        let points = velocity(&[trapezoid()], Window { from: 0.0, to: 2.0 });
        let at = |t: f64| points.iter().find(|p| (p.0 - t).abs() < 1e-9).map(|p| p.1);
        let near = |t: f64, v: f64| at(t).is_some_and(|x| (x - v).abs() < 1e-9);
        assert!(near(1.0, 0.0) && near(1.1, 100.0) && near(1.3, 100.0) && near(1.4, 0.0));
    }

    #[test]
    fn step_rate_counts_steps_per_second() {
        // 1000 steps evenly over 1 s: 1000 steps/s in every bin.
        let steps: Vec<f64> = (0..1000).map(|i| (f64::from(i) + 0.5) / 1000.0).collect();
        let r = rate(&steps, Window { from: 0.0, to: 1.0 });
        assert_eq!(r.len(), BINS);
        let total: f64 = r.iter().map(|p| p.1 / BINS as f64).sum();
        assert!((total - 1000.0).abs() < 1e-6, "{total}");
    }

    #[test]
    fn the_svg_has_both_charts_and_a_line_per_stepper() {
        let svg = svg(
            &[trapezoid()],
            &[("stepper_x", vec![1.05, 1.1]), ("stepper_y", vec![])],
            Window { from: 0.5, to: 1.5 },
        );
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<polyline").count(), 3);
        assert!(svg.contains("stepper_x") && svg.contains("toolhead velocity"));
    }
}
