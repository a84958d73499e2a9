//! ONNX export (opset 17) of the trajectory model's denoiser and of the experts' actors: the
//! same networks as standard graphs for ONNX Runtime, TensorRT and the like, built from
//! `onnx-protobuf`'s messages.
//!
//! `model.onnx` (a trajectory model of any objective and token pairing): inputs `x` (B x F: the
//! noised future, normalised), `t` (B: the noise level in [0, 1]; B x 2 for MeanFlow: the
//! interval's start and length) and `cond` (B x C: the conditioning, normalised); output `y`
//! (B x F): what flowmimic's network predicts, as the objective says (a velocity or a clean
//! sample for Flow Matching and MeanFlow, a noise or a clean sample for DDPM). The metadata
//! holds the config, objective, token layout, number of times and the normalisation statistics
//! as JSON; `examples/onnx_check.py` writes out each objective's sampler.
//!
//! `policy.onnx` (an expert): input `obs` (B x 295, or 445 with `track.observe_ahead`; raw
//! observations), output `action` (B x 69, the deterministic action); the observation
//! normalisation is folded in.

use flowmimic_model::TrajectoryModel;
use flowmimic_track::ppo::Policy;
use onnx_protobuf::attribute_proto::AttributeType;
use onnx_protobuf::tensor_proto::DataType;
use onnx_protobuf::tensor_shape_proto::{Dimension, dimension};
use onnx_protobuf::type_proto::{self, Tensor};
use onnx_protobuf::{
    AttributeProto, GraphProto, Message, ModelProto, NodeProto, OperatorSetIdProto, StringStringEntryProto,
    TensorProto, TensorShapeProto, TypeProto, ValueInfoProto,
};

pub const OPSET: i64 = 17;
/// The IR version that goes with opset 17.
const IR_VERSION: i64 = 8;
/// The `format` metadata of every exported graph.
pub const FORMAT: &str = "flowmimic-onnx/1";

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("{0}")]
    Unsupported(String),
    #[error("encoding the ONNX graph: {0}")]
    Encode(String),
}

/// A graph under construction; node outputs get fresh names.
struct Graph {
    proto: GraphProto,
    count: usize,
}

fn attribute(name: &str, kind: AttributeType, fill: impl FnOnce(&mut AttributeProto)) -> AttributeProto {
    let mut a = AttributeProto { name: name.into(), type_: kind.into(), ..Default::default() };
    fill(&mut a);
    a
}

fn int(name: &str, value: i64) -> AttributeProto {
    attribute(name, AttributeType::INT, |a| a.i = value)
}

fn ints(name: &str, values: &[i64]) -> AttributeProto {
    attribute(name, AttributeType::INTS, |a| a.ints = values.to_vec())
}

fn float(name: &str, value: f32) -> AttributeProto {
    attribute(name, AttributeType::FLOAT, |a| a.f = value)
}

/// A float tensor's type; `None` dimensions are the batch.
fn float_type(dims: &[Option<usize>]) -> TypeProto {
    let dim = |d: &Option<usize>| Dimension {
        value: Some(match d {
            Some(n) => dimension::Value::DimValue(*n as i64),
            None => dimension::Value::DimParam("batch".into()),
        }),
        ..Default::default()
    };
    let shape = TensorShapeProto { dim: dims.iter().map(dim).collect(), ..Default::default() };
    let tensor = Tensor { elem_type: DataType::FLOAT as i32, shape: Some(shape).into(), ..Default::default() };
    TypeProto { value: Some(type_proto::Value::TensorType(tensor)), ..Default::default() }
}

impl Graph {
    fn new(name: &str) -> Self {
        Self { proto: GraphProto { name: name.into(), ..Default::default() }, count: 0 }
    }

    fn fresh(&mut self, what: &str) -> String {
        self.count += 1;
        format!("{what}_{}", self.count)
    }

    fn input(&mut self, name: &str, dims: &[Option<usize>]) -> String {
        let info = ValueInfoProto { name: name.into(), type_: Some(float_type(dims)).into(), ..Default::default() };
        self.proto.input.push(info);
        name.into()
    }

    fn output(&mut self, value: &str, name: &str, dims: &[Option<usize>]) {
        self.node_named("Identity", &[value], vec![], name);
        let info = ValueInfoProto { name: name.into(), type_: Some(float_type(dims)).into(), ..Default::default() };
        self.proto.output.push(info);
    }

    /// A float initializer of shape `dims`.
    fn floats(&mut self, what: &str, dims: &[usize], values: &[f32]) -> String {
        debug_assert_eq!(dims.iter().product::<usize>(), values.len());
        let name = self.fresh(what);
        self.proto.initializer.push(TensorProto {
            name: name.clone(),
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: DataType::FLOAT as i32,
            raw_data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ..Default::default()
        });
        name
    }

    /// An int64 vector initializer (shapes, axes, split sizes).
    fn int64s(&mut self, values: &[i64]) -> String {
        let name = self.fresh("i64");
        self.proto.initializer.push(TensorProto {
            name: name.clone(),
            dims: vec![values.len() as i64],
            data_type: DataType::INT64 as i32,
            raw_data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ..Default::default()
        });
        name
    }

    fn scalar(&mut self, value: f32) -> String {
        self.floats("c", &[], &[value])
    }

    fn node_named(&mut self, op: &str, inputs: &[&str], attribute: Vec<AttributeProto>, output: &str) {
        self.proto.node.push(NodeProto {
            op_type: op.into(),
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![output.into()],
            name: format!("{op}_{}", self.proto.node.len()),
            attribute,
            ..Default::default()
        });
    }

    fn node(&mut self, op: &str, inputs: &[&str], attribute: Vec<AttributeProto>) -> String {
        let out = self.fresh(&op.to_lowercase());
        self.node_named(op, inputs, attribute, &out);
        out
    }

    fn op(&mut self, op: &str, inputs: &[&str]) -> String {
        self.node(op, inputs, vec![])
    }

    fn reshape(&mut self, x: &str, shape: &[i64]) -> String {
        let shape = self.int64s(shape);
        self.op("Reshape", &[x, &shape])
    }

    fn unsqueeze(&mut self, x: &str, axis: i64) -> String {
        let axes = self.int64s(&[axis]);
        self.op("Unsqueeze", &[x, &axes])
    }

    fn transpose(&mut self, x: &str, perm: &[i64]) -> String {
        self.node("Transpose", &[x], vec![ints("perm", perm)])
    }

    /// `x W^T + b` for a row-major `[outputs][inputs]` weight, as flowmimic's dense layers.
    fn linear(&mut self, x: &str, weight: &[f32], bias: &[f32], inputs: usize) -> String {
        let outputs = bias.len();
        let transposed: Vec<f32> =
            (0..inputs * outputs).map(|k| weight[(k % outputs) * inputs + k / outputs]).collect();
        let w = self.floats("weight", &[inputs, outputs], &transposed);
        let b = self.floats("bias", &[outputs], bias);
        let product = self.op("MatMul", &[x, &w]);
        self.op("Add", &[&product, &b])
    }

    fn encode(self, metadata: Vec<(&str, String)>) -> Result<Vec<u8>, ExportError> {
        let model = ModelProto {
            ir_version: IR_VERSION,
            opset_import: vec![OperatorSetIdProto { domain: String::new(), version: OPSET, ..Default::default() }],
            producer_name: "flowmimic".into(),
            producer_version: env!("CARGO_PKG_VERSION").into(),
            graph: Some(self.proto).into(),
            metadata_props: metadata
                .into_iter()
                .map(|(key, value)| StringStringEntryProto { key: key.into(), value, ..Default::default() })
                .collect(),
            ..Default::default()
        };
        model.write_to_bytes().map_err(|e| ExportError::Encode(e.to_string()))
    }
}

/// The trajectory model's denoiser as an ONNX graph (see the crate's documentation): every
/// objective and token pairing. Its output is the network's own (a velocity, a clean sample or
/// a noise, as the objective in its metadata says); MeanFlow's network takes two times per
/// sample, the interval's start and length.
pub fn trajectory_model(model: &TrajectoryModel) -> Result<Vec<u8>, ExportError> {
    let times = model.objective.times();
    let layout = model.layout();
    let net = &model.net.net;
    let c = net.config;
    let param = |name: &str| -> Result<&[f32], ExportError> {
        let slot = net.tensors().iter().find(|s| s.name == name);
        let slot = slot.ok_or_else(|| ExportError::Unsupported(format!("the network has no tensor '{name}'")))?;
        Ok(&net.params[slot.at..slot.at + slot.len()])
    };
    let (cond_len, future_len, window) = (layout.cond_len(), layout.future_len(), layout.window_len());
    let (tokens, token_dim, d, heads) = (c.tokens as i64, c.token_dim, c.d_model, c.heads);
    let dh = d / heads;
    let mut g = Graph::new("flowmimic_trajectory_model");
    let x = g.input("x", &[None, Some(future_len)]);
    let t = if times == 1 { g.input("t", &[None]) } else { g.input("t", &[None, Some(times)]) };
    let cond = g.input("cond", &[None, Some(cond_len)]);
    let linear = |g: &mut Graph, x: &str, name: &str, inputs: usize| -> Result<String, ExportError> {
        Ok(g.linear(x, param(&format!("{name}.weight"))?, param(&format!("{name}.bias"))?, inputs))
    };
    let layer_norm = |g: &mut Graph, x: &str, name: &str| -> Result<String, ExportError> {
        let gamma = g.floats("gamma", &[d], param(&format!("{name}.gamma"))?);
        let beta = g.floats("beta", &[d], param(&format!("{name}.beta"))?);
        Ok(g.node("LayerNormalization", &[x, &gamma, &beta], vec![int("axis", -1), float("epsilon", 1e-5)]))
    };
    // Tokens: the entries of concat(cond, x) each token entry holds, as the pairing gathers them
    // (an appended zero where it pads), cut into `tokens` rows.
    let joined = g.node("Concat", &[&cond, &x], vec![int("axis", 1)]);
    let pads = g.int64s(&[0, 0, 0, 1]);
    let padded = g.op("Pad", &[&joined, &pads]);
    let sources: Vec<i64> = model.net.token_sources().iter().map(|j| j.unwrap_or(window) as i64).collect();
    let sources = g.int64s(&sources);
    let gathered = g.node("Gather", &[&padded, &sources], vec![int("axis", 1)]);
    let input = g.reshape(&gathered, &[-1, tokens, token_dim as i64]);
    let mut h = linear(&mut g, &input, "input", token_dim)?;
    // Time(t) = sinusoids(1000 t) W_t, features [sin a_0, cos a_0, sin a_1, ...] of each time in
    // turn; two times come in hundredths.
    let half = c.time_features / times / 2;
    let freqs: Vec<f32> = (0..half).map(|j| (-(10000f32).ln() * j as f32 / half as f32).exp()).collect();
    let per_time = if times == 1 {
        g.unsqueeze(&t, 1)
    } else {
        let hundredths = g.scalar(flowmimic_model::trajectory::TWO_TIMES_SCALE);
        g.op("Mul", &[&t, &hundredths])
    };
    let thousand = g.scalar(1000.0);
    let scaled = g.op("Mul", &[&per_time, &thousand]);
    let scaled = g.unsqueeze(&scaled, 2);
    let freqs = g.floats("freqs", &[half], &freqs);
    let angles = g.op("Mul", &[&scaled, &freqs]);
    let (sin, cos) = (g.op("Sin", &[&angles]), g.op("Cos", &[&angles]));
    let (sin, cos) = (g.unsqueeze(&sin, 3), g.unsqueeze(&cos, 3));
    let pairs = g.node("Concat", &[&sin, &cos], vec![int("axis", 3)]);
    let mut features = g.reshape(&pairs, &[-1, c.time_features as i64]);
    if c.sample_features > 0 {
        // A labelled model's label (the end of cond) joins the noise level's features.
        let label: Vec<i64> = layout.label_range().map(|j| j as i64).collect();
        let label = g.int64s(&label);
        let label = g.node("Gather", &[&cond, &label], vec![int("axis", 1)]);
        features = g.node("Concat", &[&features, &label], vec![int("axis", 1)]);
    }
    let temb = linear(&mut g, &features, "time", c.time_features + c.sample_features)?;
    let temb = g.unsqueeze(&temb, 1);
    let pos = g.floats("pos", &[c.tokens, d], param("pos")?);
    let embed = g.op("Add", &[&pos, &temb]);
    h = g.op("Add", &[&h, &embed]);
    let scale = g.scalar(1.0 / (dh as f32).sqrt());
    for l in 0..c.layers {
        let block = |part: &str| format!("blocks.{l}.{part}");
        // h += Attn(LN(h)).
        let a = layer_norm(&mut g, &h, &block("ln1"))?;
        let qkv = linear(&mut g, &a, &block("qkv"), d)?;
        let split = g.int64s(&[d as i64; 3]);
        let names = [g.fresh("q"), g.fresh("k"), g.fresh("v")];
        g.proto.node.push(NodeProto {
            op_type: "Split".into(),
            input: vec![qkv, split],
            output: names.to_vec(),
            name: format!("Split_{}", g.proto.node.len()),
            attribute: vec![int("axis", 2)],
            ..Default::default()
        });
        let per_head = |g: &mut Graph, x: &str, perm: &[i64]| {
            let r = g.reshape(x, &[-1, tokens, heads as i64, dh as i64]);
            g.transpose(&r, perm)
        };
        let q = per_head(&mut g, &names[0], &[0, 2, 1, 3]);
        let k = per_head(&mut g, &names[1], &[0, 2, 3, 1]);
        let v = per_head(&mut g, &names[2], &[0, 2, 1, 3]);
        let dots = g.op("MatMul", &[&q, &k]);
        let scores = g.op("Mul", &[&dots, &scale]);
        let probs = g.node("Softmax", &[&scores], vec![int("axis", -1)]);
        let heads_out = g.op("MatMul", &[&probs, &v]);
        let merged = g.transpose(&heads_out, &[0, 2, 1, 3]);
        let merged = g.reshape(&merged, &[-1, tokens, d as i64]);
        let out = linear(&mut g, &merged, &block("proj"), d)?;
        h = g.op("Add", &[&h, &out]);
        // h += W_2 gelu(W_1 LN(h)), GELU's tanh form as flowmimic computes it.
        let b = layer_norm(&mut g, &h, &block("ln2"))?;
        let pre = linear(&mut g, &b, &block("ff1"), d)?;
        let hidden = gelu(&mut g, &pre);
        let out = linear(&mut g, &hidden, &block("ff2"), c.d_ff)?;
        h = g.op("Add", &[&h, &out]);
    }
    let last = layer_norm(&mut g, &h, "ln_out")?;
    let out = linear(&mut g, &last, "output", d)?;
    // The future read back: each entry from the token entry that predicts it.
    let flat = g.reshape(&out, &[-1, tokens * token_dim as i64]);
    let entries: Vec<i64> = model.net.output_entries()[cond_len..].iter().map(|&p| p as i64).collect();
    let entries = g.int64s(&entries);
    let future = g.node("Gather", &[&flat, &entries], vec![int("axis", 1)]);
    g.output(&future, "y", &[None, Some(future_len)]);
    let json = |v: serde_json::Result<String>| v.map_err(|e| ExportError::Encode(e.to_string()));
    g.encode(vec![
        ("format", FORMAT.into()),
        ("kind", "trajectory-model".into()),
        ("objective", json(serde_json::to_string(&model.objective))?),
        ("config", json(serde_json::to_string(&model.config))?),
        ("layout", json(serde_json::to_string(layout))?),
        ("times", times.to_string()),
        ("stats", json(serde_json::to_string(&model.stats))?),
    ])
}

/// `0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3)))`, in flowmimic's order of operations.
fn gelu(g: &mut Graph, x: &str) -> String {
    let (k, c, one, half) = (g.scalar(0.044715), g.scalar(0.797_884_6), g.scalar(1.0), g.scalar(0.5));
    let kx = g.op("Mul", &[x, &k]);
    let kx2 = g.op("Mul", &[&kx, x]);
    let kx3 = g.op("Mul", &[&kx2, x]);
    let inner = g.op("Add", &[x, &kx3]);
    let scaled = g.op("Mul", &[&inner, &c]);
    let th = g.op("Tanh", &[&scaled]);
    let gate = g.op("Add", &[&one, &th]);
    let hx = g.op("Mul", &[&half, x]);
    g.op("Mul", &[&hx, &gate])
}

/// An expert's deterministic actor with its observation normalisation folded in.
pub fn policy(policy: &Policy, clip: &str) -> Result<Vec<u8>, ExportError> {
    let n = &policy.normaliser;
    let dim = n.mean.len();
    let mut g = Graph::new("flowmimic_expert");
    let obs = g.input("obs", &[None, Some(dim)]);
    let mean: Vec<f32> = n.mean.iter().map(|&m| m as f32).collect();
    let std: Vec<f32> = n.var.iter().map(|&v| (v + 1e-8).sqrt() as f32).collect();
    let (mean, std) = (g.floats("obs_mean", &[dim], &mean), g.floats("obs_std", &[dim], &std));
    let centred = g.op("Sub", &[&obs, &mean]);
    let scaled = g.op("Div", &[&centred, &std]);
    let (lo, hi) = (g.scalar(-5.0), g.scalar(5.0));
    let mut h = g.op("Clip", &[&scaled, &lo, &hi]);
    let layers = &policy.actor.layers;
    for (i, layer) in layers.iter().enumerate() {
        h = g.linear(&h, &layer.weight, &layer.bias, layer.inputs);
        if i + 1 < layers.len() {
            h = g.node("Elu", &[&h], vec![float("alpha", 1.0)]);
        }
    }
    let actions = layers.last().map_or(0, |l| l.outputs);
    g.output(&h, "action", &[None, Some(actions)]);
    g.encode(vec![("format", FORMAT.into()), ("kind", "expert".into()), ("clip", clip.into())])
}
