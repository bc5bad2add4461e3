//! The jobs a worker has seen lately, each a replica of its propagation (`vlf_store::Replica`):
//! the geometry and the mirror maps it wrote, kept as a cache so that shooting the same
//! directions again reads memory rather than the store.

use super::*;

/// The geometry of the jobs seen last, most recent first.
pub(crate) struct Replicas {
    store: Option<(String, Store)>,
    jobs: Vec<(JobId, Replica)>,
    /// The job whose survey this worker was leased last, and what learns its parts: kept from
    /// one survey lease to the next (its atlas built once), dropped once the job's iterations
    /// come (a replica of the job is opened).
    surveying: Option<(JobId, FieldJob, Surveyor)>,
    prototypes: Option<vlf_store::Prototypes>,
    subfield_budget: Option<usize>,
}

/// How many jobs' replicas a worker keeps.
const CACHED_JOBS: usize = 2;

impl Replicas {
    /// None yet; the propagations of this process's coordinator offered through `prototypes`,
    /// if any share it; subfields held within `subfield_budget` bytes.
    pub(crate) fn new(prototypes: Option<vlf_store::Prototypes>, subfield_budget: Option<usize>) -> Replicas {
        Replicas {
            store: None,
            jobs: Vec::new(),
            surveying: None,
            prototypes,
            subfield_budget,
        }
    }

    pub(crate) fn store(&mut self, choice: &StoreChoice, server_url: &str) -> Result<Store, StoreError> {
        let url = match choice {
            StoreChoice::Handle(store) => return Ok(store.clone()),
            StoreChoice::Url(url) => url.as_str(),
            StoreChoice::FromServer => server_url,
        };
        if let Some((open, store)) = &self.store
            && open == url
        {
            return Ok(store.clone());
        }
        let store = Store::open_existing(url)?;
        self.store = Some((url.to_string(), store.clone()));
        self.jobs.clear();
        self.surveying = None;
        Ok(store)
    }

    /// The job `job`, not set up yet, and what learns its survey's parts within the worker's
    /// budget: the ones kept from the last survey lease if they are this job's.
    pub(crate) fn surveyor(&mut self, store: &Store, job: &JobId) -> Result<(&FieldJob, &Surveyor), StoreError> {
        if self.surveying.as_ref().is_none_or(|(id, _, _)| id != job) {
            self.surveying = None;
            let started = Instant::now();
            let opened = FieldJob::open(store, job)?;
            // It keeps the atlas from lease to lease, and a part's subfields (within the budget)
            // until the part is learnt: none without mirrors, where a part reads each once.
            let surveyor = Surveyor::new(opened.scene(), opened.options(), self.subfield_budget).map_err(|source| {
                StoreError::Field {
                    url: store.url().to_string(),
                    job: job.to_string(),
                    source,
                }
            })?;
            tracing::info!(
                job = %job,
                setup_s = format!("{:.2}", started.elapsed().as_secs_f64()),
                "survey geometry built"
            );
            self.surveying = Some((job.clone(), opened, surveyor));
        }
        match &self.surveying {
            Some((_, job, surveyor)) => Ok((job, surveyor)),
            None => unreachable!("set above"),
        }
    }

    pub(crate) fn replica(&mut self, store: &Store, job: &JobId) -> Result<&mut Replica, StoreError> {
        match self.jobs.iter().position(|(id, _)| id == job) {
            Some(i) => {
                let entry = self.jobs.remove(i);
                self.jobs.insert(0, entry);
            }
            None => {
                // The job's iterations have come: its survey is over.
                if self.surveying.as_ref().is_some_and(|(id, _, _)| id == job) {
                    self.surveying = None;
                }
                let opened = FieldJob::open(store, job)?;
                let taking = Instant::now();
                let replica = match self.prototypes.as_ref().and_then(|p| p.take(job)) {
                    Some(prop) => {
                        // A copy of the coordinator's propagation (or the original, for the
                        // last worker to take it), with its routes turned around: logged too.
                        let replica = Replica::at_snapshot(opened, prop);
                        tracing::info!(
                            job = %job,
                            setup_s = format!("{:.2}", taking.elapsed().as_secs_f64()),
                            "job geometry taken from this process's coordinator"
                        );
                        replica
                    }
                    None => {
                        // Every worker process builds the job's geometry for itself: the texel
                        // grids and directions; the subfields of what it shoots, as it shoots
                        // them (the discrete areas are the job's, stored with it); with mirrors,
                        // the mirror planes rasterised alone in every direction (their views) and
                        // the reflection routes. Time that more workers do not shorten
                        // (docs/scaling.md), so it is logged.
                        let started = Instant::now();
                        let replica = Replica::within(opened, self.subfield_budget)?;
                        tracing::info!(
                            job = %job,
                            setup_s = format!("{:.2}", started.elapsed().as_secs_f64()),
                            "job geometry built"
                        );
                        replica
                    }
                };
                self.jobs.insert(0, (job.clone(), replica));
                self.jobs.truncate(CACHED_JOBS);
            }
        }
        Ok(&mut self.jobs[0].1)
    }
}
