use rigbridge::daemon::config::load_run_settings;
use rigbridge::link::bind_egm;
use rigbridge::twin::egm::*;
use std::sync::Arc;
use std::time::Duration;
fn main() {
    let _ = rigbridge::stream::raise_priority(50);
    let settings = load_run_settings(std::path::Path::new("config/rigbridge.toml")).unwrap();
    let link = bind_egm("127.0.0.1:0", 6, Duration::from_millis(4)).unwrap();
    let model = EgmRobotModel::new(&settings.rig, EgmTwinSettings::default(), &settings.initial()).unwrap();
    let twin = EgmTwin::new(model, link.local_address()).unwrap();
    let control = Arc::new(EgmTwinControl::default());
    let h = spawn_egm_twin(twin, control.clone()).unwrap();
    std::thread::sleep(Duration::from_secs(2));
    control.stop.store(true, std::sync::atomic::Ordering::SeqCst);
    let twin = h.join().unwrap();
    println!("{:?}", twin.model().counters);
    println!("rt p50 {:?} p99 {:?}; link p99 {:?}", twin.round_trip_quantile_us(0.5), twin.round_trip_quantile_us(0.99), link.turnaround_quantile_us(0.99));
}
