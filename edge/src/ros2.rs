//! The live ROS 2 trolley: a camera and TF heard over Zenoh the way `rmw_zenoh` sends them, and
//! views sent to the arm's driver as ROS 2 poses. The edge's own session carries it, so a ROS 2
//! system on the same router sees this node, its topics and their types (`ros2 topic list -t`).
//!
//! Frames: the newest complete colour + depth + pose after each capture request (what is older
//! is stale: the arm was still moving). Views: the chosen one as `PoseStamped`, all of them as
//! `PoseArray`; the arm's driver answers on `view_reached` (`std_msgs/Bool`), and a refusal or a
//! timeout moves on to the next view.

use std::collections::VecDeque;
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use glasshouse_bus::DropCounters;
use glasshouse_geom::{CameraIntrinsics, FruitEstimate};
use glasshouse_pipeline::{Executed, TrolleySource};
use glasshouse_proto::{ArmState, RgbdFrame, TrolleyInfo};
use glasshouse_ros::assemble::transform_of;
use glasshouse_ros::msg::{
    decode_cdr, encode_cdr, Bool, CameraInfo, Header, Image, JointState, Pose, PoseArray,
    PoseStamped, Quaternion, RosMessage, TfMessage, Time, Vector3,
};
use glasshouse_ros::rmw::{self, Attachment, Durability, Endpoint, History, Qos, RosNode};
use glasshouse_ros::{FrameAssembler, PoseSource, RosTopics, RosTrolley, StampedFrame};
use nalgebra::Isometry3;
use serde::Deserialize;
use zenoh::Wait;

/// The ROS 2 side of the edge's settings.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ros2Settings {
    /// The ROS 2 domain (`ROS_DOMAIN_ID`).
    pub domain_id: u32,
    /// This node's name and namespace in the ROS 2 graph.
    pub node_name: String,
    pub namespace: String,
    /// How long a capture waits for a complete frame before it fails.
    pub capture_timeout_ms: u64,
    /// Views tried per answer from the planner (each refused view costs one round trip).
    pub max_view_attempts: usize,
    /// Samples waiting to be read before new ones are dropped.
    pub inbox: usize,
    /// The peers run ROS 2 Humble, whose keys carry no type hash (`TypeHashNotSupported`).
    pub humble: bool,
}

impl Default for Ros2Settings {
    fn default() -> Self {
        Self {
            domain_id: 0,
            node_name: "glasshouse_edge".into(),
            namespace: "/".into(),
            capture_timeout_ms: 30_000,
            max_view_attempts: 5,
            inbox: 256,
            humble: false,
        }
    }
}

enum Incoming {
    Colour(Vec<u8>),
    Depth(Vec<u8>),
    CameraInfo(Vec<u8>),
    Tf(Vec<u8>, bool),
    Joints(Vec<u8>),
    Reached(Vec<u8>),
}

type Sub = zenoh::pubsub::Subscriber<()>;
type Token = zenoh::liveliness::LivelinessToken;

/// A trolley driven by ROS 2.
pub struct Ros2Source {
    settings: Ros2Settings,
    topics: RosTopics,
    trolley: RosTrolley,
    assembler: FrameAssembler,
    /// Samples from the subscriber callbacks (locked only to be `Sync`: one task reads it).
    inbox: std::sync::Mutex<Receiver<Incoming>>,
    view: RosPublisher,
    ranked: RosPublisher,
    intrinsics: Option<CameraIntrinsics>,
    last_pose: Isometry3<f64>,
    _subscribers: Vec<Sub>,
    _tokens: Vec<Token>,
}

impl Ros2Source {
    /// Subscribes to the camera and TF and declares the node, its subscriptions and its
    /// publishers in the ROS 2 graph.
    pub fn open(
        session: &zenoh::Session,
        settings: Ros2Settings,
        topics: RosTopics,
        trolley: RosTrolley,
        drops: Arc<DropCounters>,
    ) -> anyhow::Result<Self> {
        topics.validate().map_err(anyhow::Error::msg)?;
        let zid = session.zid().to_string();
        let node = RosNode {
            domain: settings.domain_id,
            zid: zid.clone(),
            node_id: 0,
            namespace: settings.namespace.clone(),
            name: settings.node_name.clone(),
            enclave: String::new(),
        };
        let (tx, inbox) = sync_channel(settings.inbox.max(1));
        let mut graph = Graph::new(session, node, tx, drops.clone(), settings.humble);
        graph.node()?;
        let d = settings.domain_id;
        let qos = &topics.qos;
        graph.subscribe::<Image>(&topics.colour, &qos.camera, Incoming::Colour)?;
        graph.subscribe::<Image>(&topics.depth, &qos.camera, Incoming::Depth)?;
        graph.subscribe::<CameraInfo>(&topics.camera_info, &qos.camera, Incoming::CameraInfo)?;
        match topics.pose_source {
            PoseSource::Tf => {
                graph.subscribe::<TfMessage>(&topics.tf, &qos.tf, |b| Incoming::Tf(b, false))?;
                graph.subscribe::<TfMessage>(&topics.tf_static, &qos.tf_static, |b| {
                    Incoming::Tf(b, true)
                })?;
            }
            PoseSource::JointStates => {
                anyhow::ensure!(
                    trolley.robot.is_some(),
                    "pose_source joint_states needs the trolley's robot description (ros.trolley.robot)"
                );
                graph.subscribe::<JointState>(
                    &topics.joint_states,
                    &qos.joint_states,
                    Incoming::Joints,
                )?;
            }
        }
        graph.subscribe::<Bool>(&topics.view_reached, &qos.view_reached, Incoming::Reached)?;
        let view = graph.publisher::<PoseStamped>(&topics.view, &qos.views)?;
        let ranked = graph.publisher::<PoseArray>(&topics.ranked_views, &qos.views)?;
        tracing::info!(domain = d, node = %settings.node_name, colour = %topics.colour, pose = ?topics.pose_source, "ROS 2 source up");
        Ok(Self {
            assembler: FrameAssembler::new(topics.clone()).with_robot(trolley.robot.clone()),
            settings,
            topics,
            trolley,
            inbox: std::sync::Mutex::new(inbox),
            view,
            ranked,
            intrinsics: None,
            last_pose: Isometry3::identity(),
            _subscribers: graph.subscribers,
            _tokens: graph.tokens,
        })
    }

    fn receiver(&mut self) -> &mut Receiver<Incoming> {
        match self.inbox.get_mut() {
            Ok(inbox) => inbox,
            Err(poisoned) => poisoned.into_inner(),
        }
    }

    fn try_recv(&mut self) -> Option<Incoming> {
        self.receiver().try_recv().ok()
    }

    fn recv_until(&mut self, deadline: Instant) -> Option<Incoming> {
        let left = deadline.saturating_duration_since(Instant::now());
        self.receiver().recv_timeout(left).ok()
    }

    /// Feeds one sample to the assembler; a view answer is returned instead.
    fn take(&mut self, incoming: Incoming) -> Option<bool> {
        let decoded = match incoming {
            Incoming::Colour(b) => {
                decode_cdr::<Image>(&b, Image::TYPE_NAME).map(|m| self.assembler.push_colour(m))
            }
            Incoming::Depth(b) => {
                decode_cdr::<Image>(&b, Image::TYPE_NAME).map(|m| self.assembler.push_depth(m))
            }
            Incoming::CameraInfo(b) => decode_cdr::<CameraInfo>(&b, CameraInfo::TYPE_NAME)
                .map(|m| self.assembler.push_camera_info(m)),
            Incoming::Tf(b, is_static) => decode_cdr::<TfMessage>(&b, TfMessage::TYPE_NAME)
                .map(|m| self.assembler.push_tf(&m, is_static)),
            Incoming::Joints(b) => decode_cdr::<JointState>(&b, JointState::TYPE_NAME).map(|m| {
                if let Err(e) = self.assembler.push_joint_state(&m) {
                    tracing::warn!(topic = %self.topics.joint_states, "joint state dropped: {e}");
                }
            }),
            Incoming::Reached(b) => match decode_cdr::<Bool>(&b, Bool::TYPE_NAME) {
                Ok(answer) => return Some(answer.data),
                Err(e) => Err(e),
            },
        };
        if let Err(e) = decoded {
            self.assembler.count_corrupt();
            tracing::warn!("ROS 2 sample dropped: {e}");
        }
        None
    }

    fn collect(&mut self) -> Vec<StampedFrame> {
        let (frames, dropped) = self.assembler.poll(false);
        for d in dropped {
            tracing::warn!(
                reason = d.reason.as_str(),
                stamp_ns = d.stamp_ns,
                "ROS 2 frame dropped: {}",
                d.detail
            );
        }
        frames
    }

    /// The newest frame complete after everything queued now, waiting up to the timeout.
    fn next_frame(&mut self) -> Result<StampedFrame, String> {
        // What is queued was seen while the arm moved: assemble it, keep none of its frames.
        while let Some(incoming) = self.try_recv() {
            self.take(incoming);
        }
        let stale = self.collect().len();
        if stale > 0 {
            tracing::debug!(stale, "frames from before the capture skipped");
        }
        let deadline = Instant::now() + Duration::from_millis(self.settings.capture_timeout_ms);
        let mut ready: VecDeque<StampedFrame> = VecDeque::new();
        while ready.is_empty() {
            match self.recv_until(deadline) {
                Some(incoming) => {
                    self.take(incoming);
                    ready.extend(self.collect());
                }
                None => {
                    return Err(format!(
                        "no complete frame within {} ms on {} + {} + {} (drops so far: {:?})",
                        self.settings.capture_timeout_ms,
                        self.topics.colour,
                        self.topics.depth,
                        self.topics.tf,
                        self.assembler.drops()
                    ))
                }
            }
        }
        ready
            .pop_back()
            .context("no frame")
            .map_err(|e| e.to_string())
    }

    /// Sends `goal` as the chosen view and waits for the arm's answer (false on a timeout).
    fn try_view(&mut self, goal: &Isometry3<f64>) -> bool {
        let stamp_ns = glasshouse_bus::wall_clock_ns();
        let message = PoseStamped {
            header: Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: self.topics.world_frame.clone(),
            },
            pose: ros_pose(goal),
        };
        if let Err(e) = self.view.put(&message, stamp_ns) {
            tracing::warn!("cannot send the view: {e}");
            return false;
        }
        let deadline = Instant::now() + Duration::from_millis(self.topics.view_reached_timeout_ms);
        loop {
            match self.recv_until(deadline) {
                Some(incoming) => {
                    if let Some(reached) = self.take(incoming) {
                        return reached;
                    }
                }
                None => {
                    tracing::warn!(topic = %self.topics.view_reached, "no answer from the arm in time");
                    return false;
                }
            }
        }
    }
}

fn ros_pose(pose: &Isometry3<f64>) -> Pose {
    let t = transform_of(pose);
    Pose {
        position: Vector3 {
            x: t.translation.x,
            y: t.translation.y,
            z: t.translation.z,
        },
        orientation: Quaternion { ..t.rotation },
    }
}

impl TrolleySource for Ros2Source {
    fn info(&self) -> TrolleyInfo {
        glasshouse_ros::trolley_info(&self.trolley, self.intrinsics)
    }

    fn ground_truth(&self) -> Option<Vec<FruitEstimate>> {
        None
    }

    fn capture(&mut self, _frame_seq: u64) -> Result<Option<RgbdFrame>, String> {
        let frame = self.next_frame()?;
        self.last_pose = frame.frame.world_from_camera;
        self.intrinsics = Some(frame.frame.intrinsics);
        Ok(Some(frame.frame))
    }

    fn arm_state(&self, moving: bool, views_done: u32) -> ArmState {
        glasshouse_ros::arm_state(self.last_pose, moving, views_done)
    }

    fn execute(&mut self, goals: &[Isometry3<f64>]) -> Option<Executed> {
        let stamp_ns = glasshouse_bus::wall_clock_ns();
        let ranked = PoseArray {
            header: Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: self.topics.world_frame.clone(),
            },
            poses: goals.iter().map(ros_pose).collect(),
        };
        if let Err(e) = self.ranked.put(&ranked, stamp_ns) {
            tracing::warn!("cannot send the ranked views: {e}");
        }
        let started = Instant::now();
        let attempts = goals.len().min(self.settings.max_view_attempts);
        (0..attempts)
            .find(|&i| self.try_view(&goals[i]))
            .map(|index| Executed {
                index,
                motion_s: started.elapsed().as_secs_f64(),
            })
    }

    fn next_segment(&mut self) -> Option<f64> {
        // A ROS 2 trolley's rail is driven by its own operator: the edge stays where it is.
        None
    }
}

/// A ROS 2 publisher: its Zenoh publisher, its own id and sequence numbers (a subscriber counts
/// gaps per publisher id).
struct RosPublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
    gid: [u8; 16],
    sequence: i64,
}

impl RosPublisher {
    fn put<M: RosMessage>(&mut self, message: &M, stamp_ns: u64) -> zenoh::Result<()> {
        self.sequence += 1;
        let attachment = Attachment {
            sequence_number: self.sequence,
            source_timestamp_ns: i64::try_from(stamp_ns).unwrap_or(i64::MAX),
            source_gid: self.gid,
        };
        self.publisher
            .put(encode_cdr(message))
            .attachment(attachment.encode())
            .wait()
    }
}

/// Moves a sample's payload from a Zenoh callback to the source's inbox (a full inbox is a
/// counted overflow).
#[derive(Clone)]
struct Deliver {
    tx: SyncSender<Incoming>,
    drops: Arc<DropCounters>,
    wrap: fn(Vec<u8>) -> Incoming,
}

impl Deliver {
    fn deliver(&self, sample: &zenoh::sample::Sample) {
        let bytes = sample.payload().to_bytes().into_owned();
        if let Err(TrySendError::Full(_)) = self.tx.try_send((self.wrap)(bytes)) {
            self.drops
                .overflow
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
}

/// Declares the node's Zenoh entities and their liveliness tokens.
struct Graph<'a> {
    session: &'a zenoh::Session,
    node: RosNode,
    tx: SyncSender<Incoming>,
    drops: Arc<DropCounters>,
    humble: bool,
    next_entity: u32,
    subscribers: Vec<Sub>,
    tokens: Vec<Token>,
}

impl<'a> Graph<'a> {
    fn new(
        session: &'a zenoh::Session,
        node: RosNode,
        tx: SyncSender<Incoming>,
        drops: Arc<DropCounters>,
        humble: bool,
    ) -> Self {
        Self {
            session,
            node,
            tx,
            drops,
            humble,
            next_entity: 1,
            subscribers: Vec::new(),
            tokens: Vec::new(),
        }
    }

    fn token(&mut self, key: String) -> anyhow::Result<()> {
        let token = self
            .session
            .liveliness()
            .declare_token(key.clone())
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot declare {key}: {e}"))?;
        self.tokens.push(token);
        Ok(())
    }

    fn node(&mut self) -> anyhow::Result<()> {
        self.token(self.node.node_token())
    }

    fn subscribe<M: RosMessage>(
        &mut self,
        topic: &str,
        qos: &Qos,
        wrap: fn(Vec<u8>) -> Incoming,
    ) -> anyhow::Result<()> {
        let key = rmw::topic_subscription_key::<M>(self.node.domain, topic);
        let deliver = Deliver {
            tx: self.tx.clone(),
            drops: self.drops.clone(),
            wrap,
        };
        let live = deliver.clone();
        let subscriber = self
            .session
            .declare_subscriber(key.clone())
            .callback(move |sample| live.deliver(&sample))
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot subscribe to {key}: {e}"))?;
        self.subscribers.push(subscriber);
        if qos.durability == Durability::TransientLocal {
            self.ask_latched(&key, qos, deliver)?;
        }
        let entity = self.next_entity;
        self.next_entity += 1;
        let token =
            self.node
                .endpoint_token::<M>(entity, Endpoint::Subscription, topic, self.humble, qos);
        self.token(token)
    }

    /// Asks the latched publishers of `key` for what they kept (their last `depth` samples), as
    /// a late transient-local subscription does; the answers arrive like live samples.
    fn ask_latched(&self, key: &str, qos: &Qos, deliver: Deliver) -> anyhow::Result<()> {
        let mut cache = format!("{key}/{}", rmw::LATCHED_CACHE_SUFFIX);
        if qos.history == History::KeepLast && qos.depth > 0 {
            cache = format!("{cache}?_max={}", qos.depth);
        }
        let asked = cache.clone();
        self.session
            .get(cache.as_str())
            .accept_replies(zenoh::query::ReplyKeyExpr::Any)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(Duration::from_secs(5))
            .callback(move |reply| match reply.result() {
                Ok(sample) => deliver.deliver(sample),
                Err(e) => tracing::warn!(cache = %asked, "a latched publisher declined: {e:?}"),
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot ask {cache}: {e}"))?;
        tracing::debug!(%cache, "asked the latched publishers");
        Ok(())
    }

    fn publisher<M: RosMessage>(&mut self, topic: &str, qos: &Qos) -> anyhow::Result<RosPublisher> {
        let key = rmw::topic_key::<M>(self.node.domain, topic, self.humble);
        // As rmw_zenoh: only a reliable keep-all publisher waits for a slow subscriber.
        let congestion = match (qos.reliability, qos.history) {
            (rmw::Reliability::Reliable, History::KeepAll) => zenoh::qos::CongestionControl::Block,
            _ => zenoh::qos::CongestionControl::Drop,
        };
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .congestion_control(congestion)
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot publish on {key}: {e}"))?;
        let entity = self.next_entity;
        self.next_entity += 1;
        let token =
            self.node
                .endpoint_token::<M>(entity, Endpoint::Publisher, topic, self.humble, qos);
        let gid = rmw::publisher_gid(&token);
        self.token(token)?;
        Ok(RosPublisher {
            publisher,
            gid,
            sequence: 0,
        })
    }
}
