//! The `seasonloc` command line: argument structs (clap) and one module per subcommand.
//!
//! Raw flags are turned into validated core settings ([`SolverArgs::to_params`],
//! [`DescriptorArgs::to_spec`]) before any work starts, so a bad value fails in milliseconds with
//! a one-line reason. JSON goes to stdout, progress and logs to stderr.

pub mod eval;
pub mod npy;
pub mod solve;

use clap::{Args, Parser, Subcommand};

use crate::features::hog::{HogOptions, HogSpec};
use crate::features::Extractor;
use crate::solver::{HiddenCost, SolverParams};

/// Visual localization across seasons.
#[derive(Debug, Parser)]
#[command(name = "seasonloc", version, about, long_about = None)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Solve the data-association graph on a similarity matrix (.npy) and print the hypotheses.
    Solve(solve::SolveArgs),
    /// Localize a query image folder against a reference folder and score it against ground truth.
    Eval(eval::EvalArgs),
    /// Run the HTTP service on the embedded store (see docs/service.md).
    Serve(crate::config::ServeArgs),
}

/// Graph and solver flags shared by `solve` and `eval`.
#[derive(Debug, Clone, Args)]
pub struct SolverArgs {
    /// Fan-out K: forward edges reach the next row's columns j..=j+K.
    #[arg(long, default_value_t = 4)]
    pub fan_out: usize,
    /// Hidden (non-match) cost W: a number > 0, or `auto` (1 / the 2nd percentile of ĉ).
    #[arg(long, default_value = "auto", value_parser = parse_hidden_cost)]
    pub hidden_cost: HiddenCost,
    /// Number of flows F (route hypotheses).
    #[arg(long, default_value_t = 1)]
    pub flows: usize,
    /// Solve F > 1 as an exact min-cost flow instead of greedily.
    #[arg(long)]
    pub exact: bool,
    /// Disable horizontal edges within a row.
    #[arg(long)]
    pub no_horizontal: bool,
    /// Stop adding flows once a path's fraction of hidden rows exceeds this value (0..=1).
    #[arg(long)]
    pub stop_hidden_fraction: Option<f64>,
}

impl SolverArgs {
    /// Validated solver parameters.
    pub fn to_params(&self) -> crate::Result<SolverParams> {
        let params = SolverParams {
            fan_out: self.fan_out,
            hidden_cost: self.hidden_cost,
            flows: self.flows,
            exact: self.exact,
            horizontal: !self.no_horizontal,
            stop_hidden_fraction: self.stop_hidden_fraction,
        };
        params.validate()?;
        Ok(params)
    }
}

fn parse_hidden_cost(s: &str) -> Result<HiddenCost, String> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(HiddenCost::Auto);
    }
    match s.parse::<f64>() {
        Ok(w) if w.is_finite() && w > 0.0 => Ok(HiddenCost::Fixed(w)),
        _ => Err(format!("expected `auto` or a finite number > 0, got `{s}`")),
    }
}

/// Descriptor flags of `eval`.
#[derive(Debug, Clone, Args)]
pub struct DescriptorArgs {
    /// Global descriptor.
    #[arg(long, value_enum, default_value_t = DescriptorKind::Hog)]
    pub descriptor: DescriptorKind,
    /// HOG cell size in pixels (the paper's default is 32; use 8 for 64x32 frames).
    #[arg(long, default_value_t = 32)]
    pub cell_size: u32,
    /// Resize every image to WIDTHxHEIGHT before extraction (e.g. 640x480).
    #[arg(long, value_parser = parse_size)]
    pub resize: Option<(u32, u32)>,
}

/// Descriptor kinds available on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DescriptorKind {
    /// Histogram of oriented gradients on a dense grid of cells (flow paper III-A).
    Hog,
}

impl DescriptorArgs {
    /// The validated extractor these flags describe.
    pub fn to_extractor(&self) -> crate::Result<Box<dyn Extractor>> {
        match self.descriptor {
            DescriptorKind::Hog => Ok(Box::new(HogSpec::new(HogOptions {
                cell_size: self.cell_size,
                resize: self.resize,
            })?)),
        }
    }

    /// A short label for reports, e.g. `hog-8px`.
    pub fn label(&self) -> String {
        match self.descriptor {
            DescriptorKind::Hog => format!("hog-{}px", self.cell_size),
        }
    }
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let err = || format!("expected WIDTHxHEIGHT such as 640x480, got `{s}`");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(err)?;
    let w: u32 = w.trim().parse().map_err(|_| err())?;
    let h: u32 = h.trim().parse().map_err(|_| err())?;
    if w == 0 || h == 0 {
        return Err(err());
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_cost_accepts_auto_and_positive_numbers_only() {
        assert_eq!(parse_hidden_cost("auto"), Ok(HiddenCost::Auto));
        assert_eq!(parse_hidden_cost("1.5"), Ok(HiddenCost::Fixed(1.5)));
        for bad in ["0", "-1", "nan", "inf", "x"] {
            assert!(parse_hidden_cost(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn sizes_parse_as_width_by_height() {
        assert_eq!(parse_size("640x480"), Ok((640, 480)));
        assert!(parse_size("640").is_err());
        assert!(parse_size("0x5").is_err());
    }
}
