//! A plain f32 tensor: what weights and golden tensors are handled as.

/// A dense, row-major f32 tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    /// Dimensions, outermost first.
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values, row-major.
    pub data: Vec<f32>,
}

impl Tensor {
    /// A tensor from its shape and data; panics if they disagree (a programming error).
    pub fn new(shape: impl Into<Vec<usize>>, data: Vec<f32>) -> Self {
        let shape = shape.into();
        assert_eq!(shape.iter().product::<usize>(), data.len(), "tensor shape {shape:?} vs {} values", data.len());
        Tensor { shape, data }
    }

    /// A tensor filled with one value.
    pub fn full(shape: impl Into<Vec<usize>>, v: f32) -> Self {
        let shape = shape.into();
        let n = shape.iter().product();
        Tensor { shape, data: vec![v; n] }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True when the tensor holds no element.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The same data under another shape with as many elements.
    pub fn reshaped(mut self, shape: impl Into<Vec<usize>>) -> Self {
        let shape = shape.into();
        assert_eq!(shape.iter().product::<usize>(), self.data.len());
        self.shape = shape;
        self
    }
}

/// How far `out` is from `reference`: ‖out−ref‖/‖ref‖ and the largest absolute difference.
pub fn relative_error(out: &[f32], reference: &[f32]) -> (f64, f64) {
    let mut diff2 = 0f64;
    let mut ref2 = 0f64;
    let mut max_abs = 0f64;
    for (&a, &b) in out.iter().zip(reference) {
        let d = a as f64 - b as f64;
        diff2 += d * d;
        ref2 += (b as f64) * (b as f64);
        // NaN anywhere must show as an error, not vanish in max().
        max_abs = if d.is_nan() || d.abs() > max_abs { d.abs() } else { max_abs };
    }
    let rel = if ref2 > 0.0 { (diff2 / ref2).sqrt() } else { diff2.sqrt() };
    (rel, max_abs)
}
