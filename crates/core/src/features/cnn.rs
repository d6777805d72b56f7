//! CNN global descriptor: one named output layer of an ONNX image model, flattened and
//! L2-normalised (flow paper Section III-A uses the conv3 layer of AlexNet the same way).
//!
//! Inference runs in pure Rust with `tract-onnx`; nothing is downloaded at build or run time.
//! The model file, the layer and the preprocessing (input size, resize mode, per-channel mean and
//! scale on 0..255 RGB, NCHW) are settings ([`CnnOptions`]), so any image-classification model
//! exported to ONNX works, not only the shipped EfficientNet-Lite0.
//!
//! Why the design:
//! * [`CnnSpec::new`] does all the checking up front: it reads and hashes the file, loads and
//!   optimises the graph for the chosen output only (layers after it are never computed), and
//!   runs one zero image, so a missing file, a wrong layer name or an input size the graph cannot
//!   take fail when a map is created, not at its first query.
//! * Loading costs far more than an inference, so loaded models live in a process-wide cache
//!   keyed by (path, file sha256, layer, input size); clones and specs built from equal settings
//!   share one model behind an `Arc`. The plan is immutable and `Send + Sync`: batch extraction
//!   (rayon, one image per task) runs on all cores with that one copy.
//! * A map records [`CnnSpec::identity`] (file hash, layer, preprocessing); comparing it with the
//!   identity of the extractor at hand ([`ModelIdentity::mismatch`]) turns "localizing with a
//!   different model" into a clear error instead of silently meaningless similarities.
//!
//! Invariants: every descriptor of a spec has [`CnnSpec::dim`] values whatever the image size
//! (images are resized to the input size first), is finite, and has unit L2 norm unless the
//! layer's output is all zeros (then it stays all zeros; cosine similarity treats it as 0).

mod depthwise;
mod model;
mod preprocess;

use std::fmt;
use std::path::PathBuf;
use std::sync::Arc;

pub use self::model::NodeTime;
use self::model::{Kernels, LoadedModel};
use super::Extractor;
use crate::{Error, Result};

/// Largest accepted input side in pixels: far above any ImageNet model, and a guard against
/// a typo asking for gigabytes of activations.
pub const MAX_INPUT_SIDE: u32 = 4096;
/// Largest accepted `short_side` of the crop resize (four times [`MAX_INPUT_SIDE`]).
pub const MAX_SHORT_SIDE: u32 = 4 * MAX_INPUT_SIDE;

/// How an image is brought to the network's input size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CnnResize {
    /// Scale the short side to `short_side` (keeping the aspect ratio), then cut the centred
    /// input-size window: the usual ImageNet evaluation transform (`Resize` + `CenterCrop`).
    ShortSideCrop {
        /// Short side after scaling; at least the larger input side.
        short_side: u32,
    },
    /// Scale the whole image to the input size, ignoring its aspect ratio. Keeps the full field
    /// of view, which matters for wide, low-resolution frames such as Nordland's 64x32.
    Stretch,
}

impl fmt::Display for CnnResize {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CnnResize::ShortSideCrop { short_side } => {
                write!(f, "short side {short_side} + centre crop")
            }
            CnnResize::Stretch => f.write_str("stretch"),
        }
    }
}

/// User-facing CNN descriptor settings (validated into a [`CnnSpec`]).
#[derive(Clone, Debug, PartialEq)]
pub struct CnnOptions {
    /// Path of the `.onnx` file.
    pub model: PathBuf,
    /// Name of the output (or any node) whose value is the descriptor, e.g. `block10`.
    pub layer: String,
    /// Network input `(width, height)` in pixels; the input tensor is `[1, 3, height, width]`.
    pub input_size: (u32, u32),
    /// How images are brought to `input_size`.
    pub resize: CnnResize,
    /// Per-channel (R, G, B) value subtracted from pixels in 0..255.
    pub mean: [f32; 3],
    /// Per-channel (R, G, B) divisor applied after the mean: `x' = (x - mean) / scale`.
    pub scale: [f32; 3],
}

impl CnnOptions {
    /// The shipped EfficientNet-Lite0 (`efficientnet-lite0-224.onnx`) with the preprocessing of
    /// its README: 224x224 input, short side 256 + centre crop, `(x - 127) / 128`; layer
    /// `block10`, the closest analogue of the flow paper's AlexNet conv3.
    pub fn efficientnet_lite0(model: impl Into<PathBuf>) -> Self {
        CnnOptions {
            model: model.into(),
            layer: "block10".into(),
            input_size: (224, 224),
            resize: CnnResize::ShortSideCrop { short_side: 256 },
            mean: [127.0; 3],
            scale: [128.0; 3],
        }
    }

    /// Checks the settings that do not need the model file.
    pub fn validate(&self) -> Result<()> {
        if self.layer.trim().is_empty() {
            return Err(Error::param("cnn_layer", "the layer name is empty"));
        }
        let (w, h) = self.input_size;
        if w == 0 || h == 0 || w > MAX_INPUT_SIDE || h > MAX_INPUT_SIDE {
            return Err(Error::param(
                "cnn_input_size",
                format!("{w}x{h}: both sides must be in 1..={MAX_INPUT_SIDE}"),
            ));
        }
        if let CnnResize::ShortSideCrop { short_side } = self.resize {
            if short_side > MAX_SHORT_SIDE {
                return Err(Error::param(
                    "cnn_short_side",
                    format!("{short_side}: must be at most {MAX_SHORT_SIDE}"),
                ));
            }
            if short_side < w.max(h) {
                return Err(Error::inconsistent(
                    "cnn_short_side",
                    format!(
                        "{short_side}: must be at least the larger input side ({}) so that the \
                         {w}x{h} crop fits",
                        w.max(h)
                    ),
                ));
            }
        }
        if let Some(m) = self.mean.iter().find(|m| !m.is_finite()) {
            return Err(Error::param("cnn_mean", format!("{m} is not finite")));
        }
        // A zero, subnormal or infinite divisor turns every pixel into an infinity or NaN: the
        // divisor must be a normal f32 (|s| in f32::MIN_POSITIVE..=f32::MAX, the spec's range).
        if let Some(s) = self.scale.iter().find(|s| !s.is_normal()) {
            return Err(Error::param(
                "cnn_scale",
                format!(
                    "{s}: must be finite and non-zero, of magnitude at least {:e}",
                    f32::MIN_POSITIVE
                ),
            ));
        }
        Ok(())
    }

    /// One line describing the preprocessing; part of [`ModelIdentity`].
    pub fn preprocessing_summary(&self) -> String {
        let (w, h) = self.input_size;
        format!(
            "{w}x{h} RGB NCHW, {}, (x - {:?}) / {:?}",
            self.resize, self.mean, self.scale
        )
    }
}

/// What a map records about its CNN descriptor so that later extractors can be checked against
/// it: the same file content, layer and preprocessing give comparable descriptors.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct ModelIdentity {
    /// Lower-case hex sha256 of the ONNX file's bytes.
    pub sha256: String,
    /// The output layer used as descriptor.
    pub layer: String,
    /// [`CnnOptions::preprocessing_summary`].
    pub preprocessing: String,
}

impl ModelIdentity {
    /// `None` when `self` (e.g. recorded in a map) and `other` (the extractor at hand) give
    /// comparable descriptors, otherwise a sentence naming every difference.
    pub fn mismatch(&self, other: &ModelIdentity) -> Option<String> {
        let mut diffs = Vec::new();
        if self.sha256 != other.sha256 {
            diffs.push(format!(
                "model file sha256 {} != {}",
                self.sha256, other.sha256
            ));
        }
        if self.layer != other.layer {
            diffs.push(format!("layer `{}` != `{}`", self.layer, other.layer));
        }
        if self.preprocessing != other.preprocessing {
            diffs.push(format!(
                "preprocessing `{}` != `{}`",
                self.preprocessing, other.preprocessing
            ));
        }
        (!diffs.is_empty()).then(|| format!("different CNN descriptor: {}", diffs.join("; ")))
    }
}

impl fmt::Display for ModelIdentity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "sha256 {}, layer `{}`, {}",
            self.sha256, self.layer, self.preprocessing
        )
    }
}

/// A loaded, verified CNN descriptor; implements [`Extractor`]. Cheap to clone (the model is
/// shared).
#[derive(Clone)]
pub struct CnnSpec {
    options: CnnOptions,
    model: Arc<LoadedModel>,
}

impl fmt::Debug for CnnSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CnnSpec")
            .field("options", &self.options)
            .field("model", &self.model)
            .finish()
    }
}

impl CnnSpec {
    /// Validates `options`, then loads (or takes from the process-wide cache) the model, checks
    /// that `layer` exists and that the model runs on the input size. Errors: [`Error::Io`]
    /// naming the path when the file cannot be read; [`Error::InvalidParameter`] `cnn_model`
    /// (not a loadable ONNX model), `cnn_layer` (unknown layer, listing the model's outputs),
    /// `cnn_input_size` (the graph cannot take that input), or another `cnn_*` setting.
    pub fn new(options: CnnOptions) -> Result<Self> {
        options.validate()?;
        let model = LoadedModel::shared(&options.model, &options.layer, options.input_size)?;
        Ok(CnnSpec { options, model })
    }

    /// Like [`CnnSpec::new`] but loads a private copy of the model, bypassing the process-wide
    /// cache (neither reading nor filling it): for measuring load time, or to keep one map's
    /// model apart from the others.
    pub fn new_uncached(options: CnnOptions) -> Result<Self> {
        options.validate()?;
        let model = LoadedModel::uncached(
            &options.model,
            &options.layer,
            options.input_size,
            Kernels::Seasonloc,
        )?;
        Ok(CnnSpec {
            options,
            model: Arc::new(model),
        })
    }

    /// The settings this spec was built from.
    pub fn options(&self) -> &CnnOptions {
        &self.options
    }

    /// File hash, layer and preprocessing, for a map to record and compare.
    pub fn identity(&self) -> ModelIdentity {
        ModelIdentity {
            sha256: self.model.sha256().to_owned(),
            layer: self.options.layer.clone(),
            preprocessing: self.options.preprocessing_summary(),
        }
    }

    /// Descriptor length (the layer's flattened size), the same for every image.
    pub fn dim(&self) -> usize {
        self.model.dim()
    }

    /// The layer's output shape, batch axis included (e.g. `[1, 112, 14, 14]`).
    pub fn output_shape(&self) -> &[usize] {
        self.model.output_shape()
    }

    /// The outputs the model file declares (candidates for `layer`).
    pub fn model_outputs(&self) -> &[String] {
        self.model.outputs()
    }

    /// Whether `self` and `other` run on the same loaded model (no second copy in memory).
    pub fn shares_model_with(&self, other: &CnnSpec) -> bool {
        Arc::ptr_eq(&self.model, &other.model)
    }

    /// The network input for one image: `3 * height * width` values, planes R, G, B, after
    /// resizing and `(x - mean) / scale`. What the model sees, for inspection and benchmarks.
    pub fn preprocess(&self, image: &image::DynamicImage) -> Result<Vec<f32>> {
        preprocess::preprocess(&self.options, image)
    }

    /// Per-node wall time of `runs` inferences on `image`, slowest first: where an inference
    /// spends its time (`examples/cnn_profile.rs`).
    pub fn node_times(&self, image: &image::DynamicImage, runs: usize) -> Result<Vec<NodeTime>> {
        self.model.node_times(&self.preprocess(image)?, runs)
    }

    /// The layer's flattened output for one image, before normalisation (e.g. class logits).
    pub fn raw_output(&self, image: &image::DynamicImage) -> Result<Vec<f32>> {
        let output = self.model.run(self.preprocess(image)?)?;
        if let Some(k) = output.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: "CNN layer output",
                row: 0,
                col: k,
                value: f64::from(output[k]),
            });
        }
        Ok(output)
    }
}

impl Extractor for CnnSpec {
    fn dim_for(&self, width: u32, height: u32) -> Result<usize> {
        if width == 0 || height == 0 {
            return Err(Error::Image {
                name: "cnn input".into(),
                reason: format!("a {width}x{height} image has no pixels"),
            });
        }
        Ok(self.dim())
    }

    fn extract(&self, image: &image::DynamicImage) -> Result<Vec<f32>> {
        let mut v = self.raw_output(image)?;
        l2_normalize(&mut v);
        Ok(v)
    }
}

/// Scales `v` to unit L2 norm (accumulated in f64); an all-zero vector stays zero.
fn l2_normalize(v: &mut [f32]) {
    let norm = v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
    if norm > 0.0 {
        let inv = (1.0 / norm) as f32;
        v.iter_mut().for_each(|x| *x *= inv);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The shipped model, or `None` (with a message) when the model folder is absent
    /// (`seasonloc_test_support::datasets`).
    fn shipped_model() -> Option<PathBuf> {
        let found = seasonloc_test_support::datasets::model_file("efficientnet-lite0-224.onnx");
        if found.is_none() {
            eprintln!("SKIPPED: the CNN model efficientnet-lite0-224.onnx is absent (set SEASONLOC_DATASETS)");
        }
        found
    }

    fn spec(model: &Path, layer: &str, resize: CnnResize) -> CnnSpec {
        let mut options = CnnOptions::efficientnet_lite0(model);
        options.layer = layer.into();
        options.resize = resize;
        CnnSpec::new(options).unwrap()
    }

    fn param_error(err: &Error) -> (&'static str, &str) {
        match err {
            Error::InvalidParameter { name, reason } => (name, reason.as_str()),
            other => panic!("expected InvalidParameter, got {other:?}"),
        }
    }

    /// A parameter the model (or another parameter) rejects: [`Error::Inconsistent`].
    fn inconsistent_error(err: &Error) -> (&'static str, &str) {
        match err {
            Error::Inconsistent { name, reason } => (name, reason.as_str()),
            other => panic!("expected Inconsistent, got {other:?}"),
        }
    }

    fn top_k(values: &[f32], k: usize) -> Vec<usize> {
        let mut idx: Vec<usize> = (0..values.len()).collect();
        idx.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
        idx.truncate(k);
        idx
    }

    /// Proves that loading, preprocessing and inference are right: ordinary photos get their
    /// ImageNet classes among the top-3 `logits` (expectations from the models README).
    #[test]
    fn sample_photos_get_their_imagenet_classes_in_the_top_3() {
        let Some(model) = shipped_model() else { return };
        let dir = model.parent().expect("the model path has a folder");
        let classes = std::fs::read_to_string(dir.join("imagenet1k-classes.tsv")).unwrap();
        let names: Vec<&str> = classes
            .lines()
            .map(|l| l.split('\t').nth(1).unwrap_or(l))
            .collect();
        assert_eq!(names.len(), 1000);
        let logits = spec(
            &model,
            "logits",
            CnnResize::ShortSideCrop { short_side: 256 },
        );
        assert_eq!(logits.dim(), 1000);
        let dog_breeds: Vec<usize> = (151..=268).collect();
        let cases: [(&str, &[usize]); 4] = [
            ("dog.jpg", &dog_breeds),
            // kite, bald eagle
            ("eagle.jpg", &[21, 22]),
            // sorrel, zebra, ox, water buffalo, bison, horse cart
            ("horses.jpg", &[339, 340, 345, 346, 347, 603]),
            // zebra (ImageNet-1k has no giraffe class)
            ("giraffe.jpg", &[340]),
        ];
        for (file, expected) in cases {
            let img = image::open(dir.join("samples").join(file)).unwrap();
            let top = top_k(&logits.raw_output(&img).unwrap(), 3);
            let shown: Vec<&str> = top.iter().map(|&i| names[i]).collect();
            eprintln!("{file}: top-3 {shown:?}");
            assert!(
                top.iter().any(|i| expected.contains(i)),
                "{file}: top-3 {shown:?} has none of the expected classes"
            );
        }
    }

    #[test]
    fn descriptors_have_the_layer_size_and_unit_norm() {
        let Some(model) = shipped_model() else { return };
        let img = image::open(model.with_file_name("samples/eagle.jpg")).unwrap();
        for (layer, dim) in [
            ("pooled", 1280),
            ("block7", 15_680),
            ("block10", 21_952),
            ("block14", 9408),
        ] {
            let s = spec(&model, layer, CnnResize::Stretch);
            assert_eq!(s.dim(), dim, "{layer}");
            assert_eq!(s.dim_for(64, 32).unwrap(), dim);
            let v = s.extract(&img).unwrap();
            assert_eq!(v.len(), dim, "{layer}");
            let norm = v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
            assert!((norm - 1.0).abs() < 1e-4, "{layer}: norm {norm}");
        }
        let s = spec(&model, "block10", CnnResize::Stretch);
        assert_eq!(s.output_shape(), &[1, 112, 14, 14]);
        assert!(s.dim_for(0, 32).is_err());
    }

    #[test]
    fn identity_records_the_file_hash_layer_and_preprocessing() {
        let Some(model) = shipped_model() else { return };
        let crop = spec(
            &model,
            "block10",
            CnnResize::ShortSideCrop { short_side: 256 },
        );
        let id = crop.identity();
        assert_eq!(
            id.sha256,
            "d036cf5c80c436b500199fb5f23fe9b3a136b91bb78ada15e7c8aa6b35dd1079"
        );
        assert_eq!(id.layer, "block10");
        assert_eq!(id.mismatch(&crop.clone().identity()), None);

        let stretch = spec(&model, "block10", CnnResize::Stretch).identity();
        let why = id.mismatch(&stretch).expect("crop and stretch differ");
        assert!(
            why.contains("preprocessing") && !why.contains("layer"),
            "{why}"
        );
        let pooled = spec(
            &model,
            "pooled",
            CnnResize::ShortSideCrop { short_side: 256 },
        );
        let why = id.mismatch(&pooled.identity()).expect("layers differ");
        assert!(why.contains("layer `block10` != `pooled`"), "{why}");
        let mut other_file = id.clone();
        other_file.sha256 = "00".repeat(32);
        assert!(id.mismatch(&other_file).unwrap().contains("sha256"));
    }

    #[test]
    fn equal_settings_share_one_loaded_model() {
        let Some(model) = shipped_model() else { return };
        let a = spec(&model, "block14", CnnResize::Stretch);
        let b = spec(
            &model,
            "block14",
            CnnResize::ShortSideCrop { short_side: 300 },
        );
        let c = spec(&model, "block7", CnnResize::Stretch);
        assert!(a.shares_model_with(&a.clone()));
        // Preprocessing happens before the model, so it does not need another copy.
        assert!(a.shares_model_with(&b));
        assert!(!a.shares_model_with(&c));
        let private = CnnSpec::new_uncached(a.options().clone()).unwrap();
        assert!(!a.shares_model_with(&private));
        assert_eq!(private.identity(), a.identity());
    }

    #[test]
    fn unknown_layers_fail_at_creation_and_list_the_outputs() {
        let Some(model) = shipped_model() else { return };
        let mut options = CnnOptions::efficientnet_lite0(&model);
        options.layer = "block11".into();
        let err = CnnSpec::new(options).unwrap_err();
        let (name, reason) = inconsistent_error(&err);
        assert_eq!(name, "cnn_layer");
        assert!(reason.contains("`block11`"), "{reason}");
        for output in ["logits", "pooled", "block7", "block10", "block14"] {
            assert!(reason.contains(output), "{reason}");
        }
    }

    #[test]
    fn input_sizes_the_layer_cannot_take_fail_at_creation() {
        let Some(model) = shipped_model() else { return };
        let mut options = CnnOptions::efficientnet_lite0(&model);
        options.resize = CnnResize::Stretch;
        // block10 sits after four stride-2 stages: an 8x8 input leaves it 0x0.
        options.input_size = (8, 8);
        let err = CnnSpec::new(options).unwrap_err();
        let (name, reason) = inconsistent_error(&err);
        assert_eq!(name, "cnn_input_size");
        assert!(
            reason.contains("8x8") && reason.contains("block10"),
            "{reason}"
        );
    }

    #[test]
    fn settings_are_validated_before_the_model_is_read() {
        let base = CnnOptions::efficientnet_lite0("/nonexistent/model.onnx");
        type Edit = fn(&mut CnnOptions);
        let cases: [(&str, Edit); 8] = [
            ("cnn_layer", |o| o.layer = " ".into()),
            ("cnn_input_size", |o| o.input_size = (0, 224)),
            ("cnn_input_size", |o| o.input_size = (224, 100_000)),
            ("cnn_short_side", |o| {
                o.resize = CnnResize::ShortSideCrop {
                    short_side: 100_000,
                }
            }),
            ("cnn_mean", |o| o.mean[1] = f32::NAN),
            ("cnn_scale", |o| o.scale[2] = 0.0),
            ("cnn_scale", |o| o.scale[0] = f32::MIN_POSITIVE / 2.0),
            ("cnn_scale", |o| o.scale[1] = -f32::INFINITY),
        ];
        for (want, edit) in cases {
            let mut o = base.clone();
            edit(&mut o);
            let err = CnnSpec::new(o).unwrap_err();
            assert_eq!(param_error(&err).0, want, "{err}");
        }
        // A short side that is valid alone but smaller than the input it must hold.
        let mut o = base.clone();
        o.resize = CnnResize::ShortSideCrop { short_side: 200 };
        let err = CnnSpec::new(o).unwrap_err();
        assert_eq!(inconsistent_error(&err).0, "cnn_short_side", "{err}");
        // Valid settings get as far as reading the file, the extreme divisors too.
        let mut o = base.clone();
        o.scale = [f32::MIN_POSITIVE, -f32::MIN_POSITIVE, f32::MAX];
        assert!(matches!(CnnSpec::new(o).unwrap_err(), Error::Io { .. }));
        match CnnSpec::new(base).unwrap_err() {
            Error::Io { path, .. } => assert_eq!(path, Path::new("/nonexistent/model.onnx")),
            other => panic!("expected Io, got {other:?}"),
        }
    }

    /// Threads share one plan; each run has its own state, so results do not depend on which
    /// thread or how many run at once.
    #[test]
    fn parallel_extraction_equals_sequential_extraction() {
        use rayon::prelude::*;
        let Some(model) = shipped_model() else { return };
        let s = spec(&model, "block14", CnnResize::Stretch);
        let images: Vec<image::DynamicImage> = ["dog.jpg", "eagle.jpg", "horses.jpg"]
            .iter()
            .map(|f| image::open(model.with_file_name("samples").join(f)).unwrap())
            .collect();
        let sequential: Vec<Vec<f32>> = images.iter().map(|i| s.extract(i).unwrap()).collect();
        let parallel: Vec<Vec<f32>> = images
            .par_iter()
            .chain(images.par_iter())
            .map(|i| s.extract(i).unwrap())
            .collect();
        assert_eq!(&parallel[..3], &sequential[..]);
        assert_eq!(&parallel[3..], &sequential[..]);
    }

    /// The documented tolerance of the fast preparation path (`features::resize_rgb`, within one
    /// level of `image`'s triangle filter): descriptors of the sample photos and a Nordland frame
    /// stay within these bounds of the ones computed from `image`'s `imageops::resize`, the path
    /// used before.
    #[test]
    fn fast_resize_keeps_descriptors_within_the_documented_tolerance() {
        use image::imageops::{self, FilterType};
        let Some(model) = shipped_model() else { return };
        let s = spec(&model, "block10", CnnResize::Stretch);
        let mut files: Vec<PathBuf> = ["dog.jpg", "eagle.jpg", "horses.jpg", "giraffe.jpg"]
            .iter()
            .map(|f| model.with_file_name("samples").join(f))
            .collect();
        if let Some(nordland) = seasonloc_test_support::datasets::nordland() {
            files.push(nordland.join("winter/images-00100.png"));
        }
        for file in files {
            let img = image::open(&file).unwrap();
            let new = s.extract(&img).unwrap();
            let old_input = imageops::resize(&img.to_rgb8(), 224, 224, FilterType::Triangle);
            let mut old = s
                .model
                .run(preprocess::to_planar_for_tests(&old_input))
                .unwrap();
            l2_normalize(&mut old);
            let worst = max_abs_diff(&new, &old);
            let cos: f64 = new.iter().zip(&old).map(|(a, b)| f64::from(a * b)).sum();
            eprintln!(
                "{}: max |diff| {worst:.2e}, cosine {cos:.7}",
                file.display()
            );
            // Camera photos are shrunk to 224x224: the fast path's descriptor is within 2e-4
            // of the old one (measured: at most 1.15e-4). A 64x32 Nordland thumbnail is
            // enlarged 7x, where the two resizers' border taps differ (under 1 % of input
            // values by one level, see `image_io`): measured 1.83e-3, cosine 0.99968.
            let (tol, min_cos) = if img.width() >= 224 {
                (2e-4, 0.9999)
            } else {
                (3e-3, 0.999)
            };
            assert!(worst < tol, "{}: max |diff| {worst}", file.display());
            assert!(cos > min_cos, "{}: cosine {cos}", file.display());
        }
    }

    /// The depthwise operator that replaces tract's (`cnn/depthwise.rs`) keeps descriptors
    /// within 1e-4 of tract's own operators, on the sample photos and Nordland frames, for
    /// layers before and after the stride-2 5x5 layers and with both resize modes.
    #[test]
    fn seasonloc_depthwise_matches_tracts_operators_within_1e_4() {
        let Some(model) = shipped_model() else { return };
        let mut files: Vec<PathBuf> = ["dog.jpg", "eagle.jpg", "horses.jpg", "giraffe.jpg"]
            .iter()
            .map(|f| model.with_file_name("samples").join(f))
            .collect();
        let nordland = seasonloc_test_support::datasets::nordland().unwrap_or_default();
        for frame in ["winter/images-00100.png", "summer/images-01230.png"] {
            let path = nordland.join(frame);
            if path.is_file() {
                files.push(path);
            } else {
                eprintln!("{} absent: checking the sample photos only", path.display());
            }
        }
        let images: Vec<image::DynamicImage> =
            files.iter().map(|f| image::open(f).unwrap()).collect();
        for (layer, resize) in [
            ("block10", CnnResize::Stretch),
            ("block10", CnnResize::ShortSideCrop { short_side: 256 }),
            ("block14", CnnResize::Stretch),
            ("logits", CnnResize::Stretch),
        ] {
            let fast = spec(&model, layer, resize);
            let options = fast.options();
            let reference =
                LoadedModel::uncached(&options.model, layer, options.input_size, Kernels::Tract)
                    .unwrap();
            // EfficientNet-Lite0 has 11 depthwise layers up to block10 and 16 in all.
            assert!(fast.model.depthwise_rewritten() >= 11, "{layer}");
            assert_eq!(reference.depthwise_rewritten(), 0);
            // The 112x112 and 56x56 layers take in the convolution in front of them: the stem
            // (3x3 stride 2 after a zero `Pad`) and the 1x1 expansions of blocks 1 to 3.
            assert_eq!(fast.model.fronts_fused(), 4, "{layer}");
            for (file, img) in files.iter().zip(&images) {
                let new = fast.extract(img).unwrap();
                let mut old = reference.run(fast.preprocess(img).unwrap()).unwrap();
                l2_normalize(&mut old);
                let worst = max_abs_diff(&new, &old);
                eprintln!(
                    "{layer} {resize}, {}: max |diff| {worst:.2e}",
                    file.display()
                );
                assert!(worst < 1e-4, "{layer}, {}: {worst}", file.display());
            }
        }
    }

    /// The largest element-wise difference of two descriptors.
    fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    }

    #[test]
    fn l2_normalize_gives_unit_norm_and_keeps_zero_vectors() {
        let mut v = vec![3.0, 4.0];
        l2_normalize(&mut v);
        assert_eq!(v, vec![0.6, 0.8]);
        let mut z = vec![0.0; 4];
        l2_normalize(&mut z);
        assert_eq!(z, vec![0.0; 4]);
    }

    #[test]
    fn preprocessing_summary_names_every_setting() {
        let o = CnnOptions::efficientnet_lite0("m.onnx");
        assert_eq!(
            o.preprocessing_summary(),
            "224x224 RGB NCHW, short side 256 + centre crop, (x - [127.0, 127.0, 127.0]) / \
             [128.0, 128.0, 128.0]"
        );
    }
}
