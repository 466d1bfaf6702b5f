//! The CPU's instruction sets as one value, probed once, and the cap the environment variable
//! `PRL_ISA` puts on them, so that any machine can run (and CI can test) the lower paths of the
//! runtime's own kernels: `PRL_ISA=generic` (portable loops only), `neon` (aarch64: NEON and
//! the dot product), `avx2` (AVX2 + FMA),
//! `avx512` (AVX-512F, no VNNI or AMX), `vnni` (AVX-512 VNNI, no AMX), unset or `native`
//! (everything the CPU has). The cap applies to the runtime's operators; tract's own matrix
//! kernels choose theirs from the CPU.

use std::sync::OnceLock;

/// What the runtime's kernels may use on this machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Isa {
    /// x86_64 AVX2 with FMA.
    pub avx2_fma: bool,
    /// x86_64 AVX-512F (with AVX2 and FMA).
    pub avx512: bool,
    /// x86_64 AVX-512 VNNI (u8 x i8 dot products).
    pub vnni: bool,
    /// x86_64 AVX-512 VBMI with BW and VL (byte permutes across the register), beside VNNI: the
    /// integer depthwise convolution builds its words of four taps with them.
    pub vbmi: bool,
    /// x86_64 AMX-INT8 tiles, granted by the OS.
    pub amx: bool,
    /// aarch64 NEON (Advanced SIMD).
    pub neon: bool,
    /// aarch64 dot-product instructions (SDOT/UDOT).
    pub dotprod: bool,
    /// aarch64 half-precision arithmetic.
    pub fp16: bool,
    /// The `PRL_ISA` value in force, when one was set and understood.
    pub cap: Option<&'static str>,
}

impl Isa {
    /// Everything this CPU has.
    pub fn probe() -> Isa {
        #[allow(unused_mut)]
        let mut isa = Isa::default();
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            isa.avx2_fma = has!("avx2") && has!("fma");
            isa.avx512 = isa.avx2_fma && has!("avx512f");
            isa.vnni = isa.avx512 && has!("avx512vnni");
            isa.vbmi = isa.vnni && has!("avx512vbmi") && has!("avx512bw") && has!("avx512vl");
            isa.amx = super::ops::amx_available();
        }
        #[cfg(target_arch = "aarch64")]
        {
            use std::arch::is_aarch64_feature_detected as has;
            isa.neon = has!("neon");
            isa.dotprod = has!("dotprod");
            isa.fp16 = has!("fp16");
        }
        isa
    }

    /// This set with nothing above `cap` (`generic`, `avx2`, `avx512`, `vnni`, `native`; on
    /// aarch64 `neon` keeps NEON and the dot product, as `avx2` and above do, and drops fp16);
    /// `None` for a name it does not know.
    pub fn capped(self, cap: &str) -> Option<Isa> {
        let (level, name) = match cap.trim().to_ascii_lowercase().as_str() {
            "generic" => (0, "generic"),
            "avx2" => (1, "avx2"),
            "neon" => (1, "neon"),
            "avx512" => (2, "avx512"),
            "vnni" => (3, "vnni"),
            "native" | "" => return Some(self),
            _ => return None,
        };
        Some(Isa {
            avx2_fma: self.avx2_fma && level >= 1,
            avx512: self.avx512 && level >= 2,
            vnni: self.vnni && level >= 3,
            vbmi: self.vbmi && level >= 3,
            amx: false,
            neon: self.neon && level >= 1,
            dotprod: self.dotprod && level >= 1,
            fp16: false,
            cap: Some(name),
        })
    }

    /// One line for people: what the kernels may use, and the cap.
    pub fn describe(&self) -> String {
        let names = [
            (self.avx2_fma, "AVX2+FMA"),
            (self.avx512, "AVX-512"),
            (self.vnni, "VNNI"),
            (self.vbmi, "VBMI"),
            (self.amx, "AMX"),
            (self.neon, "NEON"),
            (self.dotprod, "dot product"),
            (self.fp16, "fp16"),
        ];
        let on: Vec<&str> = names.iter().filter(|(b, _)| *b).map(|(_, n)| *n).collect();
        let list = if on.is_empty() { "portable loops only".to_string() } else { on.join(", ") };
        match self.cap {
            Some(c) => format!("{list} (capped by PRL_ISA={c})"),
            None => list,
        }
    }
}

/// What a kernel path needs of the instruction sets.
pub type Needs = fn(&Isa) -> bool;

/// The f32 kernel paths of the runtime's operators, best first, each with what it needs: the one
/// table every operator dispatches on (a new path is a row here and an arm in each kernel).
pub const F32_KERNELS: [(F32Kernel, Needs); 4] = [
    (F32Kernel::Avx512, |i| i.avx512),
    (F32Kernel::Avx2Fma, |i| i.avx2_fma),
    (F32Kernel::Neon, |i| i.neon),
    (F32Kernel::Portable, |_| true),
];

/// One f32 kernel path (see [`F32_KERNELS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum F32Kernel {
    /// x86_64 AVX-512F (16 lanes, 32 registers), with AVX2 and FMA.
    Avx512,
    /// x86_64 AVX2 + FMA (8 lanes, 16 registers).
    Avx2Fma,
    /// aarch64 NEON (4 lanes, 32 registers), fused multiply-adds.
    Neon,
    /// Portable loops (unfused multiply-adds), for any CPU.
    Portable,
}

impl F32Kernel {
    /// The name `prl bench` prints.
    pub fn name(self) -> &'static str {
        match self {
            F32Kernel::Avx512 => "avx512",
            F32Kernel::Avx2Fma => "avx2+fma",
            F32Kernel::Neon => "neon",
            F32Kernel::Portable => "portable",
        }
    }
}

impl Isa {
    /// The best f32 path this set allows: the first row of [`F32_KERNELS`] whose needs it meets.
    pub fn f32_kernel(&self) -> F32Kernel {
        F32_KERNELS.iter().find(|(_, needs)| needs(self)).map(|(k, _)| *k).unwrap_or(F32Kernel::Portable)
    }

    /// The int8 convolution path of [`crate::PackedQConv`]: `amx`, `vnni`, `avx2`, `sdot`
    /// (aarch64's dot product), or `None` (tract's own integer matrix kernels run the int8
    /// layers).
    pub fn int8_kernel(&self) -> Option<&'static str> {
        if self.amx {
            Some("amx")
        } else if self.vnni {
            Some("vnni")
        } else if self.avx2_fma {
            Some("avx2")
        } else if self.dotprod {
            Some("sdot")
        } else {
            None
        }
    }
}

static ISA: OnceLock<Isa> = OnceLock::new();

/// The instruction sets the runtime's kernels use: the CPU's, capped by `PRL_ISA` (a value
/// it does not know leaves the CPU's, and [`isa_warning`] says so).
pub fn isa() -> &'static Isa {
    ISA.get_or_init(|| {
        let native = Isa::probe();
        match std::env::var("PRL_ISA") {
            Ok(cap) => native.capped(&cap).unwrap_or(native),
            Err(_) => native,
        }
    })
}

/// The f32 kernel path of [`isa`] ([`Isa::f32_kernel`]), chosen once: the operators ask for it
/// on every call, some of them per tile.
pub fn f32_kernel() -> F32Kernel {
    static KERNEL: OnceLock<F32Kernel> = OnceLock::new();
    *KERNEL.get_or_init(|| isa().f32_kernel())
}

/// A message when `PRL_ISA` is set to a value the runtime does not know.
pub fn isa_warning() -> Option<String> {
    let cap = std::env::var("PRL_ISA").ok()?;
    Isa::probe().capped(&cap).is_none().then(|| {
        format!(
            "PRL_ISA={cap} is not one of generic, neon, avx2, avx512, vnni, native: the CPU's own instruction sets are used"
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_only_take_away() {
        let all = Isa { avx2_fma: true, avx512: true, vnni: true, vbmi: true, amx: true, ..Isa::default() };
        let g = all.capped("generic").unwrap();
        assert!(!g.avx2_fma && !g.avx512 && !g.vnni && !g.vbmi && !g.amx);
        let a = all.capped("AVX2").unwrap();
        assert!(a.avx2_fma && !a.avx512 && !a.vnni && !a.vbmi);
        assert!(!all.capped("avx512").unwrap().vbmi);
        let v = all.capped("vnni").unwrap();
        assert!(v.avx512 && v.vnni && v.vbmi && !v.amx);
        assert_eq!(all.capped("native"), Some(all));
        assert!(all.capped("sse9").is_none());
        // A cap never adds what the CPU lacks.
        let none = Isa::default().capped("vnni").unwrap();
        assert!(!none.avx2_fma && !none.vnni);
        assert!(g.describe().contains("portable loops only"));
        // The table picks the best path a set allows.
        assert_eq!(all.f32_kernel(), F32Kernel::Avx512);
        assert_eq!(a.f32_kernel(), F32Kernel::Avx2Fma);
        assert_eq!(g.f32_kernel(), F32Kernel::Portable);
        let arm = Isa { neon: true, dotprod: true, fp16: true, ..Isa::default() };
        assert_eq!(arm.f32_kernel(), F32Kernel::Neon);
        assert_eq!(arm.capped("generic").unwrap().f32_kernel(), F32Kernel::Portable);
        assert_eq!(all.int8_kernel(), Some("amx"));
        assert_eq!(v.int8_kernel(), Some("vnni"));
        assert_eq!(a.int8_kernel(), Some("avx2"));
        assert_eq!(g.int8_kernel(), None);
        assert_eq!(arm.int8_kernel(), Some("sdot"));
        assert_eq!(arm.capped("generic").unwrap().int8_kernel(), None);
    }
}
