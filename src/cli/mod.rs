//! The `seasonloc` command line: argument structs (clap) and one module per subcommand.
//!
//! Raw flags are turned into validated core settings ([`SolverArgs::to_params`],
//! [`DescriptorArgs::to_extractor`]) before any work starts, so a bad value fails in milliseconds with
//! a one-line reason. JSON goes to stdout, progress and logs to stderr.

pub mod cooc;
pub mod eval;
pub mod ground_truth;
pub mod npy;
pub mod npz;
pub mod pickle;
pub mod plot;
pub mod record;
pub mod solve;

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};

use seasonloc_core::features::cnn::{CnnOptions, CnnResize, CnnSpec};
use seasonloc_core::features::{Extractor, Fit, Fitted};
use seasonloc_core::similarity::Normalization;
use seasonloc_core::solver::{HiddenCost, SolverParams};

/// Visual localization across seasons.
#[derive(Debug, Parser)]
#[command(name = "seasonloc", version, about, long_about = None)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands. Each takes a negative number as an option's value (`--fan-out -1`), so that the
/// option's own parser names the option and its rule instead of clap reporting an unknown
/// argument `-1`.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Solve the data-association graph on a similarity matrix (.npy) and print the hypotheses.
    #[command(allow_negative_numbers = true)]
    Solve(solve::SolveArgs),
    /// Localize a query image folder against a reference folder and score it against ground truth.
    #[command(allow_negative_numbers = true)]
    Eval(Box<eval::EvalArgs>),
    /// Run the HTTP service on the embedded store, or on PostgreSQL with `--database-url`
    /// (see docs/service.md).
    #[command(allow_negative_numbers = true)]
    Serve(Box<seasonloc_server::config::ServeArgs>),
    /// Build a map on a running service from a video or an image folder, with an optional GPS
    /// track; frames chosen by distance, time or step. Prints the map id.
    Import(Box<record::ImportArgs>),
    /// Replay a video or an image folder as a vehicle's trip against a service, writing every
    /// estimate as JSON lines or CSV.
    Drive(Box<record::DriveArgs>),
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
    pub fn to_params(&self) -> seasonloc_core::Result<SolverParams> {
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
    /// HOG input geometry: bring every image to WIDTHxHEIGHT before extraction (e.g.
    /// 640x480) [default: the size of the first reference image].
    #[arg(long, value_parser = parse_size)]
    pub resize: Option<(u32, u32)>,
    /// HOG: how an image of another size reaches the input geometry: `stretch` (resize the
    /// whole frame) or `crop` (cut the centred window of the geometry's aspect ratio first).
    #[arg(long, value_enum, default_value_t = FitArg::Stretch)]
    pub fit: FitArg,
    /// CNN: ONNX model file (an image classifier taking one [1, 3, H, W] float tensor).
    #[arg(long, env = "SEASONLOC_CNN_MODEL")]
    pub cnn_model: Option<PathBuf>,
    /// CNN: output (or node) of the model used as descriptor, e.g. `pooled`, `block10`.
    #[arg(long, default_value = "block10")]
    pub cnn_layer: String,
    /// CNN: network input size WIDTHxHEIGHT.
    #[arg(long, value_parser = parse_size, default_value = "224x224")]
    pub cnn_input: (u32, u32),
    /// CNN: how images reach the input size: `stretch` the whole frame, or `crop` (scale the
    /// short side to --cnn-short-side, cut the centre), the usual ImageNet transform.
    #[arg(long, value_enum, default_value_t = CnnResizeArg::Stretch)]
    pub cnn_resize: CnnResizeArg,
    /// CNN: short side before the centre crop [default: 256/224 of the larger input side].
    #[arg(long)]
    pub cnn_short_side: Option<u32>,
    /// CNN: per-channel mean R,G,B (or one value for all) subtracted from 0..255 pixels.
    #[arg(long, value_parser = parse_rgb, default_value = "127,127,127")]
    pub cnn_mean: [f32; 3],
    /// CNN: per-channel divisor R,G,B (or one value for all): x' = (x - mean) / scale.
    #[arg(long, value_parser = parse_rgb, default_value = "128,128,128")]
    pub cnn_scale: [f32; 3],
}

/// Descriptor kinds available on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DescriptorKind {
    /// Histogram of oriented gradients on a dense grid of cells (flow paper III-A).
    Hog,
    /// One layer of an ONNX image model, flattened and L2-normalised (flow paper III-A).
    Cnn,
}

/// `--fit` values (see `features::geometry`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FitArg {
    /// Resize the whole frame to the geometry.
    Stretch,
    /// Cut the centred window of the geometry's aspect ratio, then resize.
    Crop,
}

impl From<FitArg> for Fit {
    fn from(f: FitArg) -> Self {
        match f {
            FitArg::Stretch => Fit::Stretch,
            FitArg::Crop => Fit::Crop,
        }
    }
}

/// `--cnn-resize` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CnnResizeArg {
    /// Scale the whole image to the input size (keeps the full field of view).
    Stretch,
    /// Scale the short side, then cut the centred input-size window.
    Crop,
}

impl DescriptorArgs {
    /// The validated extractor these flags describe, for a map whose first reference image
    /// is `first_image` px (`width, height`). HOG brings every image to the input geometry
    /// (`--resize`, else `first_image`) by `--fit` (`features::geometry`); the CNN to its
    /// network input by `--cnn-resize`. For the CNN this loads the model and checks the layer
    /// and input size, so a bad model fails before any image is read.
    pub fn to_extractor(
        &self,
        first_image: (u32, u32),
    ) -> seasonloc_core::Result<Box<dyn Extractor>> {
        match self.descriptor {
            DescriptorKind::Hog => Ok(Box::new(Fitted::hog(
                self.cell_size,
                self.resize.unwrap_or(first_image),
                self.fit.into(),
            )?)),
            DescriptorKind::Cnn => {
                if self.fit != FitArg::Stretch {
                    return Err(seasonloc_core::Error::param(
                        "fit",
                        "--fit applies to HOG only; the CNN reaches its input size by \
                         --cnn-resize",
                    ));
                }
                Ok(Box::new(CnnSpec::new(self.cnn_options()?)?))
            }
        }
    }

    /// The CNN settings these flags describe (not yet checked against the model file).
    pub fn cnn_options(&self) -> seasonloc_core::Result<CnnOptions> {
        let model = self.cnn_model.clone().ok_or_else(|| {
            seasonloc_core::Error::param(
                "cnn_model",
                "--descriptor cnn needs --cnn-model PATH.onnx (or SEASONLOC_CNN_MODEL)",
            )
        })?;
        if let Some((w, h)) = self.resize {
            return Err(seasonloc_core::Error::param(
                "resize",
                format!(
                    "--resize {w}x{h} applies to HOG only; the CNN resizes to --cnn-input \
                     (see --cnn-resize)"
                ),
            ));
        }
        let (w, h) = self.cnn_input;
        let resize = match self.cnn_resize {
            CnnResizeArg::Stretch => CnnResize::Stretch,
            // 256 for 224, the ImageNet ratio, for other input sizes.
            CnnResizeArg::Crop => CnnResize::ShortSideCrop {
                short_side: self
                    .cnn_short_side
                    .unwrap_or_else(|| (w.max(h) * 256).div_ceil(224)),
            },
        };
        Ok(CnnOptions {
            model,
            layer: self.cnn_layer.clone(),
            input_size: (w, h),
            resize,
            mean: self.cnn_mean,
            scale: self.cnn_scale,
        })
    }

    /// A short label for reports, e.g. `hog-8px` or `cnn-efficientnet-lite0-224-block10-stretch`.
    pub fn label(&self) -> String {
        match self.descriptor {
            DescriptorKind::Hog => match self.fit {
                FitArg::Stretch => format!("hog-{}px", self.cell_size),
                FitArg::Crop => format!("hog-{}px-crop", self.cell_size),
            },
            DescriptorKind::Cnn => {
                let model = self
                    .cnn_model
                    .as_deref()
                    .and_then(|p| p.file_stem())
                    .map_or_else(|| "model".into(), |s| s.to_string_lossy());
                let resize = match self.cnn_resize {
                    CnnResizeArg::Stretch => "stretch".to_owned(),
                    CnnResizeArg::Crop => match self.cnn_short_side {
                        Some(s) => format!("crop{s}"),
                        None => "crop".to_owned(),
                    },
                };
                format!("cnn-{model}-{}-{resize}", self.cnn_layer)
            }
        }
    }
}

fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    let err = || format!("expected R,G,B or one number, all finite, got `{s}`");
    let values: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|_| err()))
        .collect::<Result<_, _>>()?;
    if values.iter().any(|v| !v.is_finite()) {
        return Err(err());
    }
    match values[..] {
        [v] => Ok([v; 3]),
        [r, g, b] => Ok([r, g, b]),
        _ => Err(err()),
    }
}

pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
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

    fn eval_descriptor(flags: &[&str]) -> DescriptorArgs {
        #[derive(Parser)]
        struct Wrapper {
            #[command(flatten)]
            d: DescriptorArgs,
        }
        let args = std::iter::once("seasonloc").chain(flags.iter().copied());
        Wrapper::try_parse_from(args).unwrap().d
    }

    #[test]
    fn rgb_triples_parse_with_one_value_for_all() {
        assert_eq!(parse_rgb("1,2.5,3"), Ok([1.0, 2.5, 3.0]));
        assert_eq!(parse_rgb("58.4"), Ok([58.4; 3]));
        for bad in ["1,2", "1,2,3,4", "a,b,c", "nan", ""] {
            assert!(parse_rgb(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn cnn_flags_become_cnn_options() {
        let d = eval_descriptor(&[
            "--descriptor=cnn",
            "--cnn-model=m.onnx",
            "--cnn-layer=pooled",
            "--cnn-resize=crop",
            "--cnn-input=320x240",
            "--cnn-mean=123.7,116.3,103.5",
            "--cnn-scale=58.4",
        ]);
        let o = d.cnn_options().unwrap();
        assert_eq!(o.model, PathBuf::from("m.onnx"));
        assert_eq!(o.layer, "pooled");
        assert_eq!(o.input_size, (320, 240));
        assert_eq!(o.resize, CnnResize::ShortSideCrop { short_side: 366 });
        assert_eq!(o.mean, [123.7, 116.3, 103.5]);
        assert_eq!(o.scale, [58.4; 3]);
        assert_eq!(d.label(), "cnn-m-pooled-crop");
    }

    #[test]
    fn cnn_defaults_are_the_shipped_models_with_stretch() {
        let d = eval_descriptor(&["--descriptor=cnn", "--cnn-model=dir/e.onnx"]);
        let mut want = CnnOptions::efficientnet_lite0("dir/e.onnx");
        want.resize = CnnResize::Stretch;
        assert_eq!(d.cnn_options().unwrap(), want);
        assert_eq!(d.label(), "cnn-e-block10-stretch");
    }

    #[test]
    fn cnn_without_a_model_or_with_hog_resize_is_a_clear_error() {
        let err = eval_descriptor(&["--descriptor=cnn"])
            .to_extractor((64, 32))
            .err()
            .expect("no model given");
        assert!(err.to_string().contains("--cnn-model"), "{err}");
        let err = eval_descriptor(&["--descriptor=cnn", "--cnn-model=m.onnx", "--resize=8x8"])
            .cnn_options()
            .unwrap_err();
        assert!(err.to_string().contains("HOG only"), "{err}");
    }
}

/// A `--tolerance`: reference frames, at most [`seasonloc_core::trip::MAX_TOLERANCE`].
pub fn parse_tolerance(s: &str) -> Result<usize, String> {
    let t: usize = s
        .parse()
        .map_err(|_| format!("`{s}` is not a number of frames (an integer >= 0)"))?;
    if t > seasonloc_core::trip::MAX_TOLERANCE {
        return Err(format!(
            "must be at most {}, got {t}",
            seasonloc_core::trip::MAX_TOLERANCE
        ));
    }
    Ok(t)
}

/// `--normalization` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum NormalizationArg {
    /// Eq. 2 with the column mean floored at half the median column mean (default).
    Floored,
    /// The paper's Eq. 2 exactly.
    Eq2,
    /// Raw cosine similarities.
    None,
}

impl From<NormalizationArg> for Normalization {
    fn from(n: NormalizationArg) -> Self {
        match n {
            NormalizationArg::Floored => Normalization::FlooredColumns,
            NormalizationArg::Eq2 => Normalization::Columns,
            NormalizationArg::None => Normalization::None,
        }
    }
}
