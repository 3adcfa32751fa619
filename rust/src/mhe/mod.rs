//! Moving horizon estimation (docs/user_guide/window.rst): the window problem, the models it
//! evaluates, the sliding history and the estimator that ties them to the solver.
//!
//! * [`stage`]: what a model provides at a batch of points ([`StageModel`]), and the learned
//!   model [`GpStageModel`];
//! * [`joint_arrival`]: the arrival prior of the first state and the global variables together
//!   ([`JointArrival`]), one EKF step of the pair per slide;
//! * [`learning`]: the learned model whose sparse f-GPs keep learning, their inducing outputs
//!   the window's global variables ([`LearningStageModel`]);
//! * [`learning_state`]: what an estimator with global variables carries ([`Learning`]);
//! * [`problem`]: one window as a least-squares problem ([`WindowProblem`], [`WindowEval`]),
//!   its output rows through the penalty of [`loss`];
//! * [`globals`]: global variables of the window (a model's quantities constant over it,
//!   estimated with the states) and their joint arrival prior ([`GlobalPrior`]);
//! * [`history`]: the last M + 1 steps, the arrival priors, the previous window and what the
//!   last update reported ([`outcome`]);
//! * [`lsq`]: the window as the solver's least-squares problem ([`WindowLsq`]);
//! * [`estimator`]: [`MovingHorizon`], one update = window, warm start, solve, record;
//! * [`bank`]: [`EstimatorBank`], n independent estimators updated together (in parallel).

pub mod arrival;
pub mod bank;
pub mod estimator;
pub mod globals;
pub mod history;
pub mod innovation;
pub mod joint_arrival;
pub mod learning;
pub mod learning_state;
#[cfg(test)]
mod learning_tests;
pub mod loss;
pub mod lsq;
pub mod outcome;
pub mod problem;
pub mod stage;
pub mod weights;

pub use arrival::{Arrival, ArrivalMean, ArrivalWeight};
pub use bank::{
    bank_threads, BankRow, BankSample, EstimatorBank, Member, MemberSettings, ModelState, Solution,
};
pub use estimator::{MovingHorizon, Pending, Step, UpdateReport};
pub use globals::GlobalPrior;
pub use history::{History, HistoryState, Sample, WindowData};
pub use innovation::Innovation;
pub use joint_arrival::JointArrival;
pub use learning::LearningStageModel;
pub use learning_state::{GlobalsBefore, Learning, LearningState, LearningUpdate};
pub use loss::Loss;
pub use lsq::WindowLsq;
pub use outcome::{Outcome, Solved};
pub use problem::{Form, WindowEval, WindowProblem};
pub use stage::{GpStageModel, StageEval, StageModel, GP_CACHE_PARTS};
pub use weights::Covariance;
