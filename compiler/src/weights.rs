//! Weights looked up by scoped prefix, so that the names the network asks for are the
//! checkpoint's keys; or seeded random weights for users without a checkpoint.

use std::cell::RefCell;
use std::collections::BTreeSet;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::checkpoint::{Checkpoint, Entry};
use crate::{Error, Result, Tensor};

/// How a weight is initialised when the weights are random (ignored for checkpoints).
#[derive(Debug, Clone)]
pub enum Init {
    /// He-normal for a layer with this fan-in, times `gain`.
    Fan { fan_in: usize, gain: f32 },
    /// Normal with this standard deviation around `mean`.
    Normal { mean: f32, std: f32 },
    /// Uniform in `[lo, hi)`.
    Uniform { lo: f32, hi: f32 },
    /// A fixed value (such as the sin-cos position embedding).
    Fixed(Tensor),
}

enum Source {
    Checkpoint(Checkpoint),
    Random(u64),
}

/// A source of named weights that remembers which names the network used.
pub struct Weights {
    source: Source,
    used: RefCell<BTreeSet<String>>,
}

/// A view of [`Weights`] under a key prefix (`backbone.layer1.` ...).
#[derive(Clone)]
pub struct Scope<'a> {
    weights: &'a Weights,
    prefix: String,
}

impl Weights {
    /// Weights read from a checkpoint.
    pub fn from_checkpoint(ckpt: Checkpoint) -> Self {
        Weights { source: Source::Checkpoint(ckpt), used: Default::default() }
    }

    /// Seeded random weights: the same seed always gives the same weights.
    pub fn random(seed: u64) -> Self {
        Weights { source: Source::Random(seed), used: Default::default() }
    }

    /// The root scope.
    pub fn root(&self) -> Scope<'_> {
        Scope { weights: self, prefix: String::new() }
    }

    /// The checkpoint, when the weights come from one.
    pub fn checkpoint(&self) -> Option<&Checkpoint> {
        match &self.source {
            Source::Checkpoint(c) => Some(c),
            Source::Random(_) => None,
        }
    }

    /// The random seed, when the weights are random.
    pub fn seed(&self) -> Option<u64> {
        match &self.source {
            Source::Random(s) => Some(*s),
            Source::Checkpoint(_) => None,
        }
    }

    /// Checkpoint keys the network never asked for, in order.
    pub fn unused_keys(&self) -> Vec<String> {
        let used = self.used.borrow();
        match &self.source {
            Source::Checkpoint(c) => c.entries.keys().filter(|k| !used.contains(*k)).cloned().collect(),
            Source::Random(_) => vec![],
        }
    }

    /// Keys the network asked for so far.
    pub fn used_keys(&self) -> Vec<String> {
        self.used.borrow().iter().cloned().collect()
    }

    fn source_name(&self) -> String {
        match &self.source {
            Source::Checkpoint(c) => c.path.display().to_string(),
            Source::Random(s) => format!("random weights (seed {s})"),
        }
    }

    fn get(&self, key: &str, shape: &[usize], init: &Init) -> Result<Tensor> {
        self.used.borrow_mut().insert(key.to_string());
        match &self.source {
            Source::Checkpoint(c) => {
                let missing = || Error::MissingWeight {
                    source_name: self.source_name(),
                    key: key.into(),
                    expected: shape.to_vec(),
                };
                match c.entries.get(key).ok_or_else(missing)? {
                    Entry::Tensor { tensor, .. } if tensor.shape == shape => {
                        match tensor.data.iter().filter(|v| !v.is_finite()).count() {
                            0 => Ok(tensor.clone()),
                            count => Err(Error::NonFinite { source_name: self.source_name(), key: key.into(), count }),
                        }
                    }
                    Entry::Tensor { tensor, .. } => Err(Error::WrongShape {
                        source_name: self.source_name(),
                        key: key.into(),
                        expected: shape.to_vec(),
                        actual: tensor.shape.clone(),
                    }),
                    Entry::Other(what) => {
                        Err(Error::NotATensor { source_name: self.source_name(), key: key.into(), what: what.clone() })
                    }
                }
            }
            Source::Random(seed) => Ok(random_tensor(*seed, key, shape, init)),
        }
    }
}

impl<'a> Scope<'a> {
    /// A sub-scope: `scope.pp("layer1").pp("0")` looks up `layer1.0.<name>`.
    pub fn pp(&self, name: impl std::fmt::Display) -> Scope<'a> {
        Scope { weights: self.weights, prefix: format!("{}{}.", self.prefix, name) }
    }

    /// The full key of `name` in this scope.
    pub fn key(&self, name: &str) -> String {
        format!("{}{}", self.prefix, name)
    }

    /// The weight `name`, which must have exactly `shape`.
    pub fn get(&self, name: &str, shape: &[usize], init: Init) -> Result<Tensor> {
        self.weights.get(&self.key(name), shape, &init)
    }
}

fn random_tensor(seed: u64, key: &str, shape: &[usize], init: &Init) -> Tensor {
    // Each key gets its own stream, so weights do not depend on the order they are asked for.
    let h = key.bytes().fold(0xcbf29ce484222325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100000001b3));
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ h);
    let n: usize = shape.iter().product();
    let data = match init {
        Init::Fixed(t) => return t.clone().reshaped(shape.to_vec()),
        Init::Fan { fan_in, gain } => {
            let d = Normal::new(0.0, gain * (2.0 / *fan_in as f32).sqrt()).unwrap();
            (0..n).map(|_| d.sample(&mut rng)).collect()
        }
        Init::Normal { mean, std } => {
            let d = Normal::new(*mean, *std).unwrap();
            (0..n).map(|_| d.sample(&mut rng)).collect()
        }
        Init::Uniform { lo, hi } => (0..n).map(|_| rng.random_range(*lo..*hi)).collect(),
    };
    Tensor::new(shape.to_vec(), data)
}
