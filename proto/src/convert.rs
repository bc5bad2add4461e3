//! Messages ↔ library types. [`Parameters`] is the one description of a job's settings: the
//! command line builds it from its flags (for `propagate` as well as `submit`), the server
//! validates it into [`JobSpec`], so a job means the same thing however it was started.

use crate::v1::{self, Parameters};
use vlf_core::propagate::{Options, Pass, Perturbation, Stop, defaults};
use vlf_core::psf::GridSize;
use vlf_store::Encoding;

/// A job's settings, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct JobSpec {
    pub options: Options,
    pub encoding: Encoding,
    /// Re-sample mirror maps by backward ray tracing after the last iteration.
    pub resample: bool,
    /// Keep every snapshot resumable rather than compact the superseded ones
    /// (`vlf_store::Manifest::compact`).
    pub keep_checkpoints: bool,
}

impl JobSpec {
    /// Validates `p` (unset fields take their defaults, `vlf_core::propagate::defaults`); the
    /// error names the parameter.
    pub fn from_parameters(p: &Parameters) -> Result<JobSpec, vlf_core::Error> {
        if p.iterations.is_some() && p.converge.is_some() {
            return Err(vlf_core::Error::Parameter(
                "give either a fixed iteration count or a convergence threshold, not both".into(),
            ));
        }
        let d = Options::recommended();
        let stop = match (p.iterations, p.converge) {
            (Some(k), _) => Stop::Iterations(k),
            (None, Some(epsilon)) => Stop::Converge {
                epsilon,
                max_iterations: defaults::MAX_ITERATIONS,
            },
            (None, None) => d.stop,
        };
        let options = Options {
            directions: p.directions.map_or(d.directions, |l| l as usize),
            grid: GridSize::new(p.resolution.unwrap_or(d.grid.resolution), p.tile.unwrap_or(d.grid.tile))?,
            stop,
            texel_cells: p.texel.unwrap_or(d.texel_cells),
            deferral: p.defer,
            perturbation: Perturbation {
                iterations: p.perturb.unwrap_or(d.perturbation.iterations),
                count: p.perturb_count.unwrap_or(d.perturbation.count),
            },
            // Unset: the recommended filter, only where mirrors are; given: wherever it is.
            filter_sigma: p.filter.map_or(d.filter_sigma, |f| (f != 0.0).then_some(f)),
            filter_only_with_mirrors: p.filter.is_none() && d.filter_only_with_mirrors,
            pass_batches: p.pass_batches.unwrap_or(d.pass_batches),
            stint_directions: p.stint_directions.unwrap_or(d.stint_directions),
        };
        options.validate()?;
        let encoding = match v1::Encoding::try_from(p.encoding) {
            Ok(v1::Encoding::Unspecified | v1::Encoding::F16) => Encoding::F16,
            Ok(v1::Encoding::F32) => Encoding::F32,
            Ok(v1::Encoding::Rgb9e5) => Encoding::Rgb9e5,
            Err(_) => {
                return Err(vlf_core::Error::Parameter(format!(
                    "encoding {} is not one of F32, F16, RGB9E5",
                    p.encoding
                )));
            }
        };
        Ok(JobSpec {
            options,
            encoding,
            resample: p.resample,
            keep_checkpoints: p.keep_checkpoints,
        })
    }
}

/// A pass as the two numbers of a [`v1::Lease`].
pub fn pass_to_wire(pass: Pass) -> (u32, u32) {
    match pass {
        Pass::Shoot => (0, 0),
        Pass::Areas { copy } => (1, copy),
        Pass::ShootCopy { copy } => (2, copy),
        Pass::Survey => (3, 0),
    }
}

/// Blocks of `pass` as a [`v1::PassBlocks`].
pub fn pass_blocks_to_wire(pass: Pass, blocks: &[std::ops::Range<usize>]) -> v1::PassBlocks {
    let (pass_kind, pass_copy) = pass_to_wire(pass);
    v1::PassBlocks {
        pass_kind,
        pass_copy,
        starts: blocks.iter().map(|b| b.start as u32).collect(),
        ends: blocks.iter().map(|b| b.end as u32).collect(),
    }
}

/// The pass and blocks of a [`v1::PassBlocks`], or why they are not any: an unknown pass,
/// starts and ends of different lengths, an empty or reversed block.
pub fn pass_blocks_from_wire(wire: &v1::PassBlocks) -> Result<(Pass, Vec<std::ops::Range<usize>>), String> {
    let pass = pass_from_wire(wire.pass_kind, wire.pass_copy)
        .ok_or_else(|| format!("blocks of pass ({}, {})", wire.pass_kind, wire.pass_copy))?;
    if wire.starts.len() != wire.ends.len() {
        return Err(format!(
            "blocks of {pass:?}: {} starts and {} ends",
            wire.starts.len(),
            wire.ends.len()
        ));
    }
    let blocks = (wire.starts.iter().zip(&wire.ends))
        .map(|(&s, &e)| match s < e {
            true => Ok(s as usize..e as usize),
            false => Err(format!("blocks of {pass:?}: {s}..{e} is empty")),
        })
        .collect::<Result<_, _>>()?;
    Ok((pass, blocks))
}

/// The pass of a [`v1::Lease`], if its numbers name one.
pub fn pass_from_wire(kind: u32, copy: u32) -> Option<Pass> {
    match kind {
        0 if copy == 0 => Some(Pass::Shoot),
        1 => Some(Pass::Areas { copy }),
        2 => Some(Pass::ShootCopy { copy }),
        3 if copy == 0 => Some(Pass::Survey),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_recommended_options() {
        let spec = JobSpec::from_parameters(&Parameters::default()).unwrap();
        assert_eq!(spec.options, Options::recommended());
        assert_eq!(spec.options.directions, 513);
        assert_eq!(spec.options.grid, GridSize::new(64, 8).unwrap());
        assert_eq!(
            spec.options.stop,
            Stop::Converge {
                epsilon: 1e-3,
                max_iterations: 1000
            }
        );
        assert_eq!(spec.options.filter_sigma, Some(1.0));
        assert!(spec.options.filter_only_with_mirrors);
        assert_eq!(spec.encoding, Encoding::F16);
        // A filter asked for runs wherever it is; 0 turns it off.
        let asked = |f| {
            JobSpec::from_parameters(&Parameters {
                filter: Some(f),
                ..Default::default()
            })
            .unwrap()
        };
        let on = asked(0.5).options;
        assert_eq!((on.filter_sigma, on.filter_only_with_mirrors), (Some(0.5), false));
        assert_eq!(asked(0.0).options.filter_sigma, None);
    }

    #[test]
    fn bad_parameters_name_themselves() {
        let bad = |p: Parameters, what: &str| {
            let e = JobSpec::from_parameters(&p).unwrap_err().to_string();
            assert!(e.contains(what), "`{e}` does not mention {what}");
        };
        bad(
            Parameters {
                directions: Some(100),
                ..Default::default()
            },
            "directions",
        );
        bad(
            Parameters {
                resolution: Some(60),
                tile: Some(8),
                ..Default::default()
            },
            "60",
        );
        bad(
            Parameters {
                iterations: Some(0),
                ..Default::default()
            },
            "iterations",
        );
        for pass_batches in [0, 3, 2048] {
            bad(
                Parameters {
                    pass_batches: Some(pass_batches),
                    ..Default::default()
                },
                "batches per pass",
            );
        }
        for stint_directions in [0, 3, 32] {
            bad(
                Parameters {
                    stint_directions: Some(stint_directions),
                    ..Default::default()
                },
                "directions per stint",
            );
        }
        bad(
            Parameters {
                iterations: Some(2),
                converge: Some(0.1),
                ..Default::default()
            },
            "not both",
        );
        bad(
            Parameters {
                converge: Some(f64::NAN),
                ..Default::default()
            },
            "convergence",
        );
        bad(
            Parameters {
                encoding: 17,
                ..Default::default()
            },
            "encoding",
        );
    }

    #[test]
    fn passes_round_trip() {
        for pass in [
            Pass::Shoot,
            Pass::Areas { copy: 3 },
            Pass::ShootCopy { copy: 0 },
            Pass::Survey,
        ] {
            let (k, c) = pass_to_wire(pass);
            assert_eq!(pass_from_wire(k, c), Some(pass));
        }
        assert_eq!(pass_from_wire(0, 1), None);
        assert_eq!(pass_from_wire(3, 1), None);
        assert_eq!(pass_from_wire(4, 0), None);
        let blocks = vec![0..8, 8..12, 12..13];
        let wire = pass_blocks_to_wire(Pass::Areas { copy: 3 }, &blocks);
        assert_eq!(pass_blocks_from_wire(&wire), Ok((Pass::Areas { copy: 3 }, blocks)));
        let uneven = v1::PassBlocks {
            ends: vec![8],
            ..wire.clone()
        };
        assert!(
            pass_blocks_from_wire(&uneven)
                .unwrap_err()
                .contains("3 starts and 1 ends")
        );
        let empty = v1::PassBlocks {
            starts: vec![4],
            ends: vec![4],
            ..wire.clone()
        };
        assert!(pass_blocks_from_wire(&empty).unwrap_err().contains("4..4 is empty"));
        let unknown = v1::PassBlocks { pass_kind: 7, ..wire };
        assert!(pass_blocks_from_wire(&unknown).is_err());
    }
}
