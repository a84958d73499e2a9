//! Progress of long work: a bar on a terminal, one line per update in logs (nohup, CI).

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::time::Instant;

pub struct Progress {
    bar: Option<ProgressBar>,
    total: usize,
    started: Instant,
}

impl Progress {
    /// Work of `total` units, `done` of them already done (a resumed run).
    pub fn new(total: usize, done: usize) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(total as u64).with_position(done as u64);
            bar.set_style(
                ProgressStyle::with_template("{bar:30} {pos}/{len} [{elapsed} < {eta}] {msg}").expect("template"),
            );
            bar
        });
        Self { bar, total, started: Instant::now() }
    }

    /// Reports `done` units with a status line.
    pub fn update(&self, done: usize, status: &str) {
        match &self.bar {
            Some(bar) => {
                bar.set_position(done as u64);
                bar.set_message(status.to_string());
            }
            None => eprintln!("[{done:>5}/{}] {status}  {:.0} s", self.total, self.started.elapsed().as_secs_f64()),
        }
    }

    pub fn finish(self) {
        if let Some(bar) = self.bar {
            bar.finish();
        }
    }
}

/// A CSV log of a training run, rewritten atomically at each checkpoint.
pub struct CsvLog {
    path: std::path::PathBuf,
    header: String,
    pub rows: Vec<String>,
}

impl CsvLog {
    /// A new log, or on resume the existing one cut back to rows whose first column is at
    /// most `upto` (what the checkpoint has seen).
    pub fn open(path: std::path::PathBuf, header: &str, resume_upto: Option<usize>) -> Self {
        let rows = match resume_upto {
            None => Vec::new(),
            Some(upto) => flowmimic_io::read_to_string(&path)
                .unwrap_or_default()
                .lines()
                .skip(1)
                .filter(|l| l.split(',').next().and_then(|i| i.parse::<usize>().ok()).is_some_and(|i| i <= upto))
                .map(String::from)
                .collect(),
        };
        Self { path, header: header.to_string(), rows }
    }

    pub fn save(&self) -> Result<(), flowmimic_io::FileError> {
        let text: String = std::iter::once(&self.header).chain(&self.rows).flat_map(|l| [l.as_str(), "\n"]).collect();
        flowmimic_io::write_atomic(&self.path, text.as_bytes())
    }

    /// Column `k` against column `x` of every row.
    pub fn column(&self, x: usize, k: usize) -> Vec<(f64, f64)> {
        column(&self.rows, x, k)
    }
}

/// Column `k` against column `x` of CSV rows (rows where either is not a number are skipped).
pub fn column(rows: &[String], x: usize, k: usize) -> Vec<(f64, f64)> {
    rows.iter()
        .filter_map(|r| {
            let f: Vec<&str> = r.split(',').collect();
            Some((f.get(x)?.parse().ok()?, f.get(k)?.parse().ok()?))
        })
        .collect()
}
