//! Rendering speed: one 640x480 RGB-D frame of scenario 2 from its initial camera pose (the
//! issue's target is 25 ms on one core), and scene generation.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glasshouse_sim::{CameraModel, ScenarioKind, Scene};

fn render(c: &mut Criterion) {
    let scene = Scene::generate(ScenarioKind::Two, 3);
    let camera = CameraModel::paper_default();
    let pose = scene.initial_camera_pose();
    let mut group = c.benchmark_group("render");
    group.throughput(Throughput::Elements(camera.intrinsics.pixel_count() as u64));
    group.bench_function("scenario2_640x480", |b| {
        let mut noise_seed = 0;
        b.iter(|| {
            noise_seed += 1;
            scene.render(&camera, &pose, noise_seed)
        })
    });
    group.finish();
    c.bench_function("generate_scenario2", |b| {
        b.iter(|| Scene::generate(ScenarioKind::Two, 3))
    });
}

criterion_group!(benches, render);
criterion_main!(benches);
