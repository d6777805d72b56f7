//! Loading an ONNX model with tract, once per process: parse, pick the output layer, fix the
//! input shape, optimise, make it runnable, and prove it runs by feeding one zero input.
//!
//! Why: a model that cannot serve a map must fail when the map is created (missing file, not
//! ONNX, unknown layer, input size the graph cannot take), not at the first query; and loading
//! plus optimising costs far more than one inference, so every extractor built from the same
//! (file, layer, input size) shares one [`LoadedModel`] through a process-wide cache.
//!
//! Invariants: a [`LoadedModel`] has exactly one input of shape `[1, 3, h, w]` (f32) and one
//! output whose flattened length is [`LoadedModel::dim`] > 0; its plan is immutable and
//! `Send + Sync`, so one copy serves all threads (each run gets its own scratch state).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};
use tract_onnx::prelude::*;

use super::depthwise;
use crate::{Error, Result};

/// Which implementation runs the depthwise convolutions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Kernels {
    /// [`depthwise::DepthwiseConv`] (with the clamp after it): what every extractor uses.
    Seasonloc,
    /// tract's own operators only: the reference the fast path is tested against.
    #[cfg_attr(not(test), allow(dead_code))]
    Tract,
}

/// A model ready to run: the optimised tract plan computing one chosen output.
pub(crate) struct LoadedModel {
    plan: Arc<TypedSimplePlan>,
    path: PathBuf,
    sha256: String,
    input_size: (u32, u32),
    output_shape: Vec<usize>,
    outputs: Vec<String>,
    /// Depthwise convolutions run by [`depthwise::DepthwiseConv`] instead of tract.
    depthwise_rewritten: usize,
    /// Of those, how many compute the convolution in front of them too.
    fronts_fused: usize,
}

/// Time spent in one node of the plan (`LoadedModel::node_times` in this file).
#[derive(Clone, Debug)]
pub struct NodeTime {
    /// Operator kind, e.g. `OptMatMul` or `SeasonlocDepthwiseConv`.
    pub op: String,
    /// Node name in the optimised graph.
    pub name: String,
    /// Output shape.
    pub shape: String,
    /// Summed over all timed runs.
    pub total: std::time::Duration,
}

/// (canonical path, file sha256, layer, input size): what makes two loads interchangeable.
type CacheKey = (PathBuf, String, String, (u32, u32));

/// Loaded models of this process. A handful of entries at most (one per model file, layer and
/// input size in use), so a vector with a linear scan is enough; the lock is held while a model
/// loads so that concurrent map creations never load the same model twice.
static CACHE: Mutex<Vec<(CacheKey, Arc<LoadedModel>)>> = Mutex::new(Vec::new());

impl std::fmt::Debug for LoadedModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LoadedModel")
            .field("path", &self.path)
            .field("sha256", &self.sha256)
            .field("input_size", &self.input_size)
            .field("output_shape", &self.output_shape)
            .field("depthwise_rewritten", &self.depthwise_rewritten)
            .field("fronts_fused", &self.fronts_fused)
            .finish_non_exhaustive()
    }
}

impl LoadedModel {
    /// The shared model for `(path, layer, input_size)`: from the cache when the file's content
    /// (sha256) is unchanged, otherwise loaded, verified and cached.
    pub(crate) fn shared(path: &Path, layer: &str, input_size: (u32, u32)) -> Result<Arc<Self>> {
        let (bytes, sha256) = read_and_hash(path)?;
        let canonical = std::fs::canonicalize(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let key: CacheKey = (canonical, sha256, layer.to_owned(), input_size);
        // A panic while loading cannot leave the vector half-updated, so a poisoned lock is safe
        // to keep using.
        let mut cache = CACHE
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some((_, model)) = cache.iter().find(|(k, _)| *k == key) {
            return Ok(Arc::clone(model));
        }
        let model = Arc::new(Self::load(
            path,
            &bytes,
            key.1.clone(),
            layer,
            input_size,
            Kernels::Seasonloc,
        )?);
        cache.push((key, Arc::clone(&model)));
        Ok(model)
    }

    /// A private copy of the model, neither taken from nor added to the cache.
    pub(crate) fn uncached(
        path: &Path,
        layer: &str,
        input_size: (u32, u32),
        kernels: Kernels,
    ) -> Result<Self> {
        let (bytes, sha256) = read_and_hash(path)?;
        Self::load(path, &bytes, sha256, layer, input_size, kernels)
    }

    fn load(
        path: &Path,
        bytes: &[u8],
        sha256: String,
        layer: &str,
        (width, height): (u32, u32),
        kernels: Kernels,
    ) -> Result<Self> {
        let shown = path.display();
        let bad_model = |what: &str, e: TractError| {
            Error::inconsistent("cnn_model", format!("{shown}: {what}: {e:#}"))
        };
        let onnx = tract_onnx::onnx();
        let proto = onnx
            .proto_model_for_read(&mut &bytes[..])
            .map_err(|e| bad_model("not an ONNX model", e))?;
        // The directory resolves tensors stored as external data next to the model file.
        let dir = path.parent().and_then(Path::to_str);
        let parsed = onnx
            .parse(&proto, dir)
            .map_err(|e| bad_model("cannot be loaded", e))?;
        if !parsed.unresolved_inputs.is_empty() {
            return Err(Error::inconsistent(
                "cnn_model",
                format!(
                    "{shown}: cannot be loaded: unresolved inputs {:?}",
                    parsed.unresolved_inputs
                ),
            ));
        }
        let mut model = parsed.model;
        let inputs = model
            .input_outlets()
            .map_err(|e| bad_model("no inputs", e))?;
        if inputs.len() != 1 {
            return Err(Error::inconsistent(
                "cnn_model",
                format!(
                    "{shown}: has {} inputs; seasonloc feeds one image tensor [1, 3, h, w]",
                    inputs.len()
                ),
            ));
        }
        let declared = model
            .input_fact(0)
            .map(|f| format!("{f:?}"))
            .unwrap_or_else(|_| "unknown".into());
        let outputs = output_names(&model);
        model.select_outputs_by_name([layer]).map_err(|_| {
            Error::inconsistent(
                "cnn_layer",
                format!(
                    "`{layer}` is neither an output nor a node of {shown}; its outputs are: {}",
                    outputs.join(", ")
                ),
            )
        })?;
        let shape = [1, 3, height as usize, width as usize];
        let wrong_size = |e: TractError| {
            Error::inconsistent(
                "cnn_input_size",
                format!(
                    "{shown} cannot run on a {width}x{height} input (tensor {shape:?}; the model \
                     declares {declared}): {e:#}"
                ),
            )
        };
        let mut typed = model
            .with_input_fact(0, f32::fact(shape).into())
            .and_then(|m| m.into_typed())
            .and_then(|m| m.into_decluttered())
            .map_err(wrong_size)?;
        let (depthwise_rewritten, fronts_fused) = match kernels {
            Kernels::Seasonloc => depthwise::rewrite(&mut typed)
                .map_err(|e| bad_model("depthwise convolutions cannot be rewritten", e))?,
            Kernels::Tract => (0, 0),
        };
        let plan = typed
            .into_optimized()
            .map_err(wrong_size)?
            .into_runnable()
            .map_err(|e| bad_model("cannot be made runnable", e))?;
        let mut loaded = LoadedModel {
            plan,
            path: path.to_path_buf(),
            sha256,
            input_size: (width, height),
            output_shape: Vec::new(),
            outputs,
            depthwise_rewritten,
            fronts_fused,
        };
        // Running one zero image proves that the input size is accepted end to end and gives
        // the true output shape (symbolic shapes are only resolved by running).
        let zeros = vec![0.0; 3 * width as usize * height as usize];
        let (output, out_shape) = loaded.run_raw(zeros).map_err(wrong_size)?;
        if output.is_empty() {
            return Err(Error::inconsistent(
                "cnn_input_size",
                format!(
                    "{width}x{height} is too small for `{layer}` of {shown}: the layer has no \
                     values (shape {out_shape:?})"
                ),
            ));
        }
        loaded.output_shape = out_shape;
        Ok(loaded)
    }

    /// Runs the network on one preprocessed image (`3 * h * w` values, planar RGB) and returns
    /// the chosen output, flattened.
    pub(crate) fn run(&self, input: Vec<f32>) -> Result<Vec<f32>> {
        let (output, shape) = self.run_raw(input).map_err(|e| self.inference_failed(e))?;
        if shape != self.output_shape {
            return Err(Error::Shape(format!(
                "{} produced an output of shape {shape:?}, expected {:?}",
                self.path.display(),
                self.output_shape
            )));
        }
        Ok(output)
    }

    fn run_raw(&self, input: Vec<f32>) -> TractResult<(Vec<f32>, Vec<usize>)> {
        let outputs = self.plan.run(tvec!(self.input_tensor(input)?.into()))?;
        let out = outputs
            .first()
            .ok_or_else(|| TractError::msg("the model returned no output"))?;
        let out = out.cast_to::<f32>()?;
        let values = out.to_plain_array_view::<f32>()?.iter().copied().collect();
        Ok((values, out.shape().to_vec()))
    }

    /// One preprocessed image (`3 * h * w` values, planar RGB) as the `[1, 3, h, w]` input.
    fn input_tensor(&self, input: Vec<f32>) -> TractResult<Tensor> {
        let (w, h) = self.input_size;
        Ok(
            tract_ndarray::Array4::from_shape_vec((1, 3, h as usize, w as usize), input)?
                .into_tensor(),
        )
    }

    /// The error of an inference that tract refused or failed.
    fn inference_failed(&self, e: TractError) -> Error {
        Error::inconsistent(
            "cnn_model",
            format!("inference with {} failed: {e:#}", self.path.display()),
        )
    }

    /// Wall time of every node of the plan over `runs` inferences on `input` (after one
    /// untimed run), slowest first: `(operator, node name, output shape, total time)`.
    pub(crate) fn node_times(&self, input: &[f32], runs: usize) -> Result<Vec<NodeTime>> {
        let failed = |e: TractError| self.inference_failed(e);
        let tensor = self.input_tensor(input.to_vec()).map_err(failed)?;
        let mut totals = vec![std::time::Duration::ZERO; self.plan.model().nodes().len()];
        for run in 0..=runs {
            let mut state = self.plan.spawn().map_err(failed)?;
            state
                .run_plan_with_eval(
                    tvec!(tensor.clone().into()),
                    |ctx, op_state, node, inputs| {
                        let start = std::time::Instant::now();
                        let out = tract_onnx::tract_core::plan::eval(ctx, op_state, node, inputs);
                        if run > 0 {
                            totals[node.id] += start.elapsed();
                        }
                        out
                    },
                )
                .map_err(failed)?;
        }
        let graph = self.plan.model();
        let mut times: Vec<NodeTime> = graph
            .nodes()
            .iter()
            .map(|node| NodeTime {
                op: node.op().name().to_string(),
                name: node.name.clone(),
                shape: node
                    .outputs
                    .first()
                    .map(|o| format!("{:?}", o.fact.shape))
                    .unwrap_or_default(),
                total: totals[node.id],
            })
            .collect();
        times.sort_by_key(|t| std::cmp::Reverse(t.total));
        Ok(times)
    }

    /// How many depthwise convolutions run on [`depthwise::DepthwiseConv`].
    #[cfg(test)]
    pub(crate) fn depthwise_rewritten(&self) -> usize {
        self.depthwise_rewritten
    }

    /// How many of those also compute the convolution in front of them.
    #[cfg(test)]
    pub(crate) fn fronts_fused(&self) -> usize {
        self.fronts_fused
    }

    /// Flattened output length.
    pub(crate) fn dim(&self) -> usize {
        self.output_shape.iter().product()
    }

    /// Output shape, batch axis included.
    pub(crate) fn output_shape(&self) -> &[usize] {
        &self.output_shape
    }

    /// Lower-case hex sha256 of the model file's bytes.
    pub(crate) fn sha256(&self) -> &str {
        &self.sha256
    }

    /// Names of the outputs the model file declares.
    pub(crate) fn outputs(&self) -> &[String] {
        &self.outputs
    }
}

fn output_names(model: &InferenceModel) -> Vec<String> {
    model
        .output_outlets()
        .map(|outlets| {
            outlets
                .iter()
                .map(|o| {
                    model
                        .outlet_label(*o)
                        .map_or_else(|| model.node(o.node).name.clone(), str::to_owned)
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Reads a model file and hashes it. The file is opened without blocking (`O_NONBLOCK`: a
/// FIFO put at the model's path must not hold a CPU-pool thread until a writer comes) and must
/// be a regular file by the opened handle's own metadata (not a FIFO, a device such as
/// `/dev/zero` behind a link, or a directory); at most the length that metadata gives is read,
/// so a file that grows while it is read cannot make the read unbounded.
fn read_and_hash(path: &Path) -> Result<(Vec<u8>, String)> {
    use std::io::Read;
    let io = |source| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(Error::inconsistent(
            "cnn_model",
            format!(
                "{}: not a regular file (a model is read only from a regular file)",
                path.display()
            ),
        ));
    }
    let len = meta.len();
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    file.take(len).read_to_end(&mut bytes).map_err(io)?;
    let sha256 = sha256_hex(&bytes);
    Ok((bytes, sha256))
}

fn sha256_hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    let mut hex = String::with_capacity(64);
    for b in Sha256::digest(bytes) {
        // Writing to a String cannot fail.
        let _ = write!(hex, "{b:02x}");
    }
    hex
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_is_lower_case_hex_of_the_bytes() {
        // The FIPS 180-2 test vector for "abc".
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn garbage_files_are_rejected_as_cnn_model() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("not-a-model.onnx");
        std::fs::write(&path, b"this is not protobuf \xff\xff\xff").unwrap();
        let err = LoadedModel::shared(&path, "logits", (224, 224)).unwrap_err();
        match &err {
            Error::Inconsistent { name, reason } => {
                assert_eq!(*name, "cnn_model");
                assert!(reason.contains("not-a-model.onnx"), "{reason}");
            }
            other => panic!("expected cnn_model error, got {other:?}"),
        }
    }

    /// A FIFO or a link to `/dev/zero` at a model's path is refused at once: before the
    /// non-blocking open and the regular-file check, the FIFO held the reading thread until a
    /// writer came (the test's bounded wait failed) and `/dev/zero` was read until memory ran out.
    #[cfg(unix)]
    #[test]
    fn fifos_and_devices_at_a_model_path_are_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo.onnx");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if !made.is_ok_and(|s| s.success()) {
            eprintln!("skipped: mkfifo is not available");
            return;
        }
        let zero = dir.path().join("zero.onnx");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        for path in [fifo, zero] {
            let (tx, rx) = std::sync::mpsc::channel();
            let p = path.clone();
            std::thread::spawn(move || {
                let _ = tx.send(LoadedModel::shared(&p, "x", (8, 8)).map(|_| ()));
            });
            let got = rx
                .recv_timeout(std::time::Duration::from_secs(10))
                .unwrap_or_else(|_| {
                    panic!("loading {} did not return within 10 s", path.display())
                });
            match got {
                Err(Error::Inconsistent { name, reason }) => {
                    assert_eq!(name, "cnn_model");
                    assert!(reason.contains("not a regular file"), "{reason}");
                }
                other => panic!(
                    "{}: expected a cnn_model error, got {other:?}",
                    path.display()
                ),
            }
        }
    }

    #[test]
    fn missing_files_are_io_errors_naming_the_path() {
        let err = LoadedModel::shared(Path::new("/nonexistent/m.onnx"), "x", (8, 8)).unwrap_err();
        match err {
            Error::Io { path, .. } => assert_eq!(path, Path::new("/nonexistent/m.onnx")),
            other => panic!("expected Io, got {other:?}"),
        }
    }
}
