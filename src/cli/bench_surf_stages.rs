//! `visnav bench surf --stages`: where SURF's time goes, stage by stage, on one thread (integral
//! image, response layers, extrema, orientation, descriptors), each the median of the runs. The
//! stages run as [`Surf::detect_and_describe_staged`] runs them (all orientations, then all
//! descriptors); the features are the one-pass path's, bit for bit, so the stages' sum is within
//! a few per cent of the one-pass time the main table reports.

use std::time::Instant;

use visnav::vision::{GrayImage, Surf, SurfStage};

/// One image and mode's stage medians (one thread), milliseconds.
#[derive(serde::Serialize)]
pub struct StageTiming {
    pub image: String,
    pub mode: &'static str,
    pub features: usize,
    /// `(stage name, median ms)` in the order of [`SurfStage::ALL`].
    pub stages_ms: Vec<(&'static str, f64)>,
    /// The median of the runs' totals (not the sum of the stage medians).
    pub total_ms: f64,
}

/// The median of each stage over `runs` runs of `surf` on `img`, on a one-thread pool.
pub fn time_stages(
    pool: &rayon::ThreadPool,
    surf: &Surf,
    img: &GrayImage,
    runs: usize,
) -> (Vec<(&'static str, f64)>, f64, usize) {
    pool.install(|| {
        let _ = surf.detect_and_describe(img); // warm-up
        let n_stages = SurfStage::ALL.len();
        let mut per_stage: Vec<Vec<f64>> = vec![Vec::with_capacity(runs); n_stages];
        let mut totals = Vec::with_capacity(runs);
        let mut features = 0;
        for _ in 0..runs.max(1) {
            let t0 = Instant::now();
            let mut last = t0;
            let mut i = 0;
            let f = surf.detect_and_describe_staged(img, &mut |_| {
                let now = Instant::now();
                if let Some(v) = per_stage.get_mut(i) {
                    v.push((now - last).as_secs_f64() * 1e3);
                }
                last = now;
                i += 1;
            });
            totals.push(t0.elapsed().as_secs_f64() * 1e3);
            features = f.len();
        }
        let stages = SurfStage::ALL
            .iter()
            .zip(per_stage.iter_mut())
            .map(|(s, v)| (s.name(), median(v)))
            .collect();
        (stages, median(&mut totals), features)
    })
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The stage table as text.
pub fn print(rows: &[StageTiming], runs: usize) {
    println!();
    println!("SURF stages, one thread, median of {runs} runs (ms)");
    print!("{:<38} {:>8} {:>8}", "image", "mode", "features");
    for s in SurfStage::ALL {
        print!(" {:>11}", s.name());
    }
    println!(" {:>8}", "total");
    for r in rows {
        let name = std::path::Path::new(&r.image)
            .file_name()
            .map_or(r.image.clone(), |s| s.to_string_lossy().into_owned());
        print!("{:<38} {:>8} {:>8}", name, r.mode, r.features);
        for (_, ms) in &r.stages_ms {
            print!(" {ms:>11.3}");
        }
        println!(" {:>8.2}", r.total_ms);
    }
}
