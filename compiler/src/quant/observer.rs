//! Activation ranges from calibration data: running min/max plus magnitude histograms, and the
//! four ways of turning them into a quantisation range (min/max, a percentile, the entropy/KL
//! criterion of TensorRT's calibrator, or the least squared error). A tensor whose every value
//! was a whole number in `[0, 255]` (the image crops the networks read) gets that range whatever
//! the method: scale 1 and zero point 0 quantise it without loss.

/// How an activation's range is chosen from what calibration saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// The smallest and largest values seen.
    MinMax,
    /// Clip each side at a percentile of the values on that side (outliers saturate).
    Percentile,
    /// The clipping threshold whose quantised distribution loses the least information
    /// (Kullback-Leibler divergence over a 2048-bin histogram, as TensorRT's entropy calibrator).
    Entropy,
    /// The range whose u8 quantisation has the least expected squared error on the values seen:
    /// clipping error of the values outside it plus rounding error (`step²/12`) of those inside,
    /// each side's end chosen among the histogram's bin edges.
    Mse,
}

impl Method {
    /// Every method, in the order they are documented.
    pub const ALL: [Method; 4] = [Method::MinMax, Method::Percentile, Method::Entropy, Method::Mse];

    /// The name used on the command line and in manifests.
    pub fn name(self) -> &'static str {
        match self {
            Method::MinMax => "minmax",
            Method::Percentile => "percentile",
            Method::Entropy => "entropy",
            Method::Mse => "mse",
        }
    }

    /// The method called `name`, if any.
    pub fn parse(name: &str) -> Option<Method> {
        Method::ALL.into_iter().find(|m| m.name() == name)
    }
}

/// Share of each side's values the percentile method keeps inside the range.
pub const PERCENTILE: f64 = 0.9999;
const BINS: usize = 2048;

/// Everything calibration learned about one tensor.
#[derive(Debug, Clone)]
pub struct Observer {
    min: f32,
    max: f32,
    count: u64,
    /// Width of one histogram bin; the histograms cover `[0, BINS * width)`.
    width: f32,
    /// Magnitudes of the positive values.
    pos: Vec<u64>,
    /// Magnitudes of the negative values.
    neg: Vec<u64>,
    /// Every value seen so far was a whole number in `[0, 255]`.
    bytes: bool,
}

impl Default for Observer {
    fn default() -> Self {
        Observer {
            min: f32::INFINITY,
            max: f32::NEG_INFINITY,
            count: 0,
            width: 0.0,
            pos: vec![0; BINS],
            neg: vec![0; BINS],
            bytes: true,
        }
    }
}

impl Observer {
    /// Record a batch of values (NaN is ignored: it has no place in a range).
    pub fn observe(&mut self, data: &[f32]) {
        let (mut lo, mut hi) = (self.min, self.max);
        for &v in data {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        (self.min, self.max) = (lo, hi);
        self.bytes = self.bytes && data.iter().all(|&v| v.is_nan() || (v.fract() == 0.0 && (0.0..=255.0).contains(&v)));
        let top = hi.abs().max(lo.abs());
        if !top.is_finite() || top == 0.0 {
            self.count += data.len() as u64;
            if top == 0.0 {
                self.pos[0] += data.len() as u64;
            }
            return;
        }
        if self.width == 0.0 {
            self.width = top / BINS as f32;
        }
        // Grow the histograms by merging pairs of bins until the new extreme fits.
        while top >= self.width * BINS as f32 {
            for h in [&mut self.pos, &mut self.neg] {
                for i in 0..BINS / 2 {
                    h[i] = h[2 * i] + h[2 * i + 1];
                }
                h[BINS / 2..].iter_mut().for_each(|b| *b = 0);
            }
            self.width *= 2.0;
        }
        let inv = 1.0 / self.width;
        for &v in data {
            if v.is_nan() {
                continue;
            }
            let bin = ((v.abs() * inv) as usize).min(BINS - 1);
            if v < 0.0 {
                self.neg[bin] += 1;
            } else {
                self.pos[bin] += 1;
            }
        }
        self.count += data.len() as u64;
    }

    /// Smallest and largest values seen (`None` before any finite value).
    pub fn min_max(&self) -> Option<(f32, f32)> {
        (self.min <= self.max).then_some((self.min, self.max))
    }

    /// The range `method` chooses, widened to hold 0 (so that zero is exact, as padding needs);
    /// `[0, 255]` for a tensor of whole numbers in that range (u8 holds it exactly).
    pub fn range(&self, method: Method) -> Option<(f32, f32)> {
        let (lo, hi) = self.min_max()?;
        if self.bytes {
            return Some((0.0, 255.0));
        }
        let (lo, hi) = match method {
            Method::MinMax => (lo, hi),
            Method::Percentile => {
                (-self.percentile(&self.neg, PERCENTILE).min(-lo), self.percentile(&self.pos, PERCENTILE).min(hi))
            }
            Method::Entropy => {
                let t = self.entropy_threshold(lo >= 0.0);
                (lo.max(-t), hi.min(t))
            }
            Method::Mse => {
                let (n, p) = self.mse_ends();
                (lo.max(-n), hi.min(p))
            }
        };
        Some((lo.min(0.0), hi.max(0.0)))
    }

    /// The magnitude below which `share` of a side's values lie (upper edge of that bin).
    fn percentile(&self, h: &[u64], share: f64) -> f32 {
        let total: u64 = h.iter().sum();
        if total == 0 {
            return 0.0;
        }
        let want = (share * total as f64).ceil() as u64;
        let mut acc = 0;
        for (i, &c) in h.iter().enumerate() {
            acc += c;
            if acc >= want {
                return (i + 1) as f32 * self.width;
            }
        }
        BINS as f32 * self.width
    }

    /// The magnitudes (negative side, positive side) that end the least-squared-error range.
    /// Each side's values beyond its end `t` cost `Σ c·(x − t)²` (`x` a bin's centre), computed
    /// from suffix sums of `c`, `c·x` and `c·x²`; every value costs `step²/12` with
    /// `step = (t₋ + t₊)/255`. Every pair of bin edges up to each side's last value is tried.
    fn mse_ends(&self) -> (f32, f32) {
        let w = self.width as f64;
        // Per side, the clipping cost at each candidate end (edge k·w, k = 0..=last bin + 1).
        let clip = |h: &[u64]| -> Vec<f64> {
            let last = h.iter().rposition(|&c| c > 0).map_or(0, |i| i + 1);
            let mut costs = vec![0.0; last + 1];
            let (mut c, mut s1, mut s2) = (0.0, 0.0, 0.0);
            for k in (0..last).rev() {
                let x = (k as f64 + 0.5) * w;
                let n = h[k] as f64;
                (c, s1, s2) = (c + n, s1 + n * x, s2 + n * x * x);
                let t = k as f64 * w;
                costs[k] = s2 - 2.0 * t * s1 + t * t * c;
            }
            costs
        };
        let (neg, pos) = (clip(&self.neg), clip(&self.pos));
        let total = self.count as f64;
        let mut best = (f64::INFINITY, neg.len() - 1, pos.len() - 1);
        for (i, &cn) in neg.iter().enumerate() {
            for (j, &cp) in pos.iter().enumerate() {
                let step = (i + j) as f64 * w / 255.0;
                let cost = cn + cp + total * step * step / 12.0;
                if cost < best.0 {
                    best = (cost, i, j);
                }
            }
        }
        (best.1 as f32 * self.width, best.2 as f32 * self.width)
    }

    /// TensorRT's entropy calibration on the magnitude histogram: the threshold whose
    /// clipped-and-requantised distribution is closest (KL) to the observed one. `unsigned`
    /// tensors get 256 levels, signed ones 128 per side.
    fn entropy_threshold(&self, unsigned: bool) -> f32 {
        let hist: Vec<f64> = self.pos.iter().zip(&self.neg).map(|(&p, &n)| (p + n) as f64).collect();
        let levels = if unsigned { 255 } else { 128 };
        let last = hist.iter().rposition(|&c| c > 0.0).map_or(0, |i| i + 1);
        if last <= levels {
            return last as f32 * self.width;
        }
        let mut best = (f64::INFINITY, last);
        for i in levels..=last {
            let mut p: Vec<f64> = hist[..i].to_vec();
            p[i - 1] += hist[i..].iter().sum::<f64>();
            let q = requantise(&hist[..i], levels);
            let kl = kl_divergence(&p, &q);
            if kl < best.0 {
                best = (kl, i);
            }
        }
        best.1 as f32 * self.width
    }
}

/// Merge `p` into `levels` buckets, then spread each bucket evenly over its non-empty bins.
fn requantise(p: &[f64], levels: usize) -> Vec<f64> {
    let n = p.len();
    let mut q = vec![0.0; n];
    for j in 0..levels {
        let (start, end) = (j * n / levels, ((j + 1) * n / levels).max(j * n / levels + 1).min(n));
        let sum: f64 = p[start..end].iter().sum();
        let nonzero = p[start..end].iter().filter(|&&c| c > 0.0).count();
        if nonzero > 0 {
            for k in start..end {
                if p[k] > 0.0 {
                    q[k] = sum / nonzero as f64;
                }
            }
        }
    }
    q
}

/// KL(p || q) of two unnormalised histograms; bins where `p` is empty contribute nothing, and a
/// bin where only `q` is empty is smoothed rather than infinite.
fn kl_divergence(p: &[f64], q: &[f64]) -> f64 {
    let (sp, sq): (f64, f64) = (p.iter().sum(), q.iter().sum());
    if sp == 0.0 || sq == 0.0 {
        return 0.0;
    }
    p.iter()
        .zip(q)
        .filter(|(&a, _)| a > 0.0)
        .map(|(&a, &b)| {
            let (a, b) = (a / sp, (b / sq).max(1e-12));
            a * (a / b).ln()
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minmax_is_exact_and_holds_zero() {
        let mut o = Observer::default();
        o.observe(&[1.5, 3.0, 2.0]);
        assert_eq!(o.range(Method::MinMax), Some((0.0, 3.0)));
        o.observe(&[-2.0, 40.0]);
        assert_eq!(o.range(Method::MinMax), Some((-2.0, 40.0)));
    }

    #[test]
    fn whole_numbers_in_a_byte_keep_every_level() {
        // Pixels: every method gives [0, 255] (scale 1), even where a percentile would clip.
        let mut data: Vec<f32> = (0..100_000).map(|i| (i % 200) as f32).collect();
        data.extend([251.0, 0.0]);
        let mut o = Observer::default();
        o.observe(&data);
        for m in Method::ALL {
            assert_eq!(o.range(m), Some((0.0, 255.0)), "{m:?}");
        }
        // One fraction, or one value outside a byte, and it is an ordinary tensor again.
        for odd in [7.5, 256.0, -1.0] {
            let mut o = Observer::default();
            o.observe(&data);
            o.observe(&[odd]);
            assert_ne!(o.range(Method::MinMax), Some((0.0, 255.0)), "{odd}");
        }
    }

    #[test]
    fn percentile_and_entropy_clip_a_few_outliers() {
        // Exponential quantiles (a ReLU-like long tail up to about 11.5) and a few outliers.
        let n = 100_000;
        let mut data: Vec<f32> = (0..n).map(|i| -(((i as f64 + 0.5) / n as f64).ln()) as f32).collect();
        data.extend([40.0; 5]);
        let mut o = Observer::default();
        o.observe(&data);
        let (_, hi) = o.range(Method::Percentile).unwrap();
        assert!(hi > 8.0 && hi < 12.0, "percentile threshold {hi}");
        let (_, hi) = o.range(Method::Entropy).unwrap();
        assert!(hi > 4.0 && hi < 20.0, "entropy threshold {hi}");
        assert_eq!(o.range(Method::MinMax).unwrap().1, 40.0);
    }

    #[test]
    fn mse_clips_where_the_squared_error_is_least() {
        // Uniform values on [-1, 1] and one far outlier at 100. Min/max spends the levels on
        // it: step 101/255, rounding error step²/12 = 0.013 on every value. Among two million
        // values (a calibration tensor holds tens of millions) clipping it part of the way costs
        // less (at t: (100 - t)² plus the finer step's rounding error; least near t = 27); among
        // a hundred thousand, clipping it only a little (least near t = 89).
        let bulk = |n: usize| (0..n).map(move |i| -1.0 + 2.0 * (i as f32 + 0.5) / n as f32);
        let mut o = Observer::default();
        o.observe(&bulk(2_000_000).chain([100.0]).collect::<Vec<_>>());
        let (lo, hi) = o.range(Method::Mse).unwrap();
        assert!((-1.05..=-0.95).contains(&lo) && (20.0..=35.0).contains(&hi), "mse range {lo}..{hi}");
        let mut o = Observer::default();
        o.observe(&bulk(100_000).chain([100.0]).collect::<Vec<_>>());
        let hi = o.range(Method::Mse).unwrap().1;
        assert!((80.0..100.0).contains(&hi), "mse range ..{hi}");
        // Where half the values are far out, clipping them costs more than the coarse step.
        let mut o = Observer::default();
        o.observe(&[-100.0, 100.0, -100.0, 100.0, 0.5, -0.5, 0.25, -0.25]);
        let (lo, hi) = o.range(Method::Mse).unwrap();
        assert!(lo < -95.0 && hi > 95.0, "mse range {lo}..{hi}");
    }

    #[test]
    fn histograms_grow_without_losing_counts() {
        let mut o = Observer::default();
        o.observe(&[0.5; 10]);
        o.observe(&[-300.0, 300.0]);
        assert_eq!(o.pos.iter().sum::<u64>() + o.neg.iter().sum::<u64>(), 12);
        assert!(o.width * BINS as f32 > 300.0);
    }
}
