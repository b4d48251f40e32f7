#include "server_cloud/backend/schur_solver.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <thread>
#include <unordered_map>
#include <utility>

#include <ceres/cost_function.h>
#include <Eigen/CholmodSupport>
#include <Eigen/Dense>
#include <Eigen/SparseCore>

#include "common/core/steady_clock.hpp"
#include "common/factors/manifolds.hpp"
#include "common/factors/state_layout.hpp"
#include "common/factors/world_point_factor.hpp"

namespace cvislam::server::backend {

namespace {

using Clock = std::chrono::steady_clock;
using Mat33 = Eigen::Matrix3d;
using Mat63 = Eigen::Matrix<double, 6, 3>;
using Mat66 = Eigen::Matrix<double, 6, 6>;
using Vec3 = Eigen::Vector3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using SparseMatrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;

// Ceres' Levenberg-Marquardt constants, so that both solvers take the same steps.
constexpr double kMinDiagonal = 1e-6;
constexpr double kMaxDiagonal = 1e32;
constexpr double kMinRelativeDecrease = 1e-3;
constexpr double kInitialRadius = 1e4;
constexpr double kMaxRadius = 1e16;
constexpr double kMinRadius = 1e-32;
constexpr double kParameterTolerance = 1e-8;

// Runs f(part, begin, end) over [0, n) cut into `parts` contiguous ranges, each but the first on a thread of its
// own. `parts` is also the number of accumulators the caller keeps, so it never depends on n.
template <class F>
void splitOver(int parts, std::size_t n, const F& f) {
  if (parts <= 1) {
    f(0, std::size_t{0}, n);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(static_cast<std::size_t>(parts - 1));
  const auto bound = [&](int part) { return n * static_cast<std::size_t>(part) / static_cast<std::size_t>(parts); };
  for (int part = 1; part < parts; ++part) pool.emplace_back([&, part] { f(part, bound(part), bound(part + 1)); });
  f(0, std::size_t{0}, bound(1));
  for (std::thread& t : pool) t.join();
}

// Cauchy: rho(s) = b log(1 + s / b), b = scale^2; the residual and its Jacobian are scaled by sqrt(rho'(s)).
struct Robust {
  double rho;
  double weight;
};
Robust cauchy(double s, double b) {
  return {b * std::log1p(s / b), std::sqrt(1.0 / (1.0 + s / b))};
}

double clampDiagonal(double d) {
  return std::clamp(d, kMinDiagonal, kMaxDiagonal);
}

}  // namespace

struct SchurProblem::Impl {
  struct KeyframeBlock {
    double* x = nullptr;
    int size = 0;     // ambient
    int tangent = 0;  // in the reduced system
    bool pose = false;
    bool held = false;
    int offset = -1;  // in the reduced system; -1 when held
  };
  struct PointBlock {
    double* x = nullptr;
    bool held = false;
  };
  struct Reprojection {
    std::unique_ptr<factors::WorldPointReprojectionFactor> factor;
    int pose = 0;
    int point = 0;
    double b = 1.0;  // the Cauchy scale squared
  };
  struct KeyframeFactor {
    std::unique_ptr<ceres::CostFunction> factor;
    std::vector<int> blocks;
    std::vector<int> pairs;  // per (i <= j) of `blocks`, row-major upper triangle: the pair, or -1 (a held side)
  };
  // One block of the reduced matrix's upper triangle: rows of keyframe block `row`, columns of block `col`
  // (row <= col), stored column-major at `value`.
  struct Pair {
    int row = 0;
    int col = 0;
    std::size_t value = 0;
    int row_in_column = 0;  // where its rows start among the stored entries of each of its columns
  };

  std::vector<KeyframeBlock> keyframe_blocks;
  std::vector<PointBlock> points;
  std::vector<Reprojection> reprojections;
  std::vector<KeyframeFactor> keyframe_factors;

  // The structure, built once per solve().
  int dim = 0;
  std::vector<Pair> pairs;
  std::size_t values_size = 0;
  std::vector<int> diagonal_pair;             // per keyframe block
  std::vector<int> obs_start;                 // per point, into obs
  std::vector<int> obs;                       // reprojections, by point then pose
  std::vector<int> obs_slot;                  // per entry of obs: the point's slot of its pose, or -1 (held)
  std::vector<int> slot_start;                // per point, into slot_pose and W
  std::vector<int> slot_pose;                 // free poses that see the point
  std::vector<std::size_t> point_pair_start;  // per point, into point_pairs
  std::vector<int> point_pairs;               // per (slot a <= slot b) of each point
  std::vector<int> column_start;              // the CSC index of each reduced column's first stored entry
  SparseMatrix reduced;
  std::unique_ptr<Eigen::CholmodDecomposition<SparseMatrix, Eigen::Upper>> cholmod;

  // The linearisation at the accepted state: the keyframe part of J^T J and J^T r, each point's 3x3 block, its
  // J^T r and its couplings W = J_pose^T J_point per slot.
  std::vector<double> C;
  Eigen::VectorXd gc;
  std::vector<Mat33> Hpp;
  std::vector<Vec3> bp;
  std::vector<Mat63> W;
  double cost_at = 0.0;

  // Per part (thread) scratch: a reduced matrix and right-hand side each; part 0 writes to S and g.
  std::vector<std::vector<double>> part_values;
  std::vector<Eigen::VectorXd> part_rhs;
  std::vector<double> part_cost;
  std::vector<std::uint8_t> part_failed;
  std::vector<double> S;
  Eigen::VectorXd g;
  std::vector<Mat33> Hinv;
  std::vector<Vec3> point_diagonal;
  Eigen::VectorXd keyframe_diagonal;
  Eigen::VectorXd dc;
  std::vector<Vec3> dp;
  std::vector<double> backup;
  // Each pose block's rotation matrix and position, converted once per evaluation pass rather than per
  // observation.
  std::vector<Mat33> R_w_s;
  std::vector<Vec3> p_w_s;

  int pairOf(int a, int b, std::unordered_map<std::uint64_t, int>& index) {
    const int lo = std::min(a, b);
    const int hi = std::max(a, b);
    const std::uint64_t key = (static_cast<std::uint64_t>(lo) << 32U) | static_cast<std::uint32_t>(hi);
    const auto [it, added] = index.emplace(key, static_cast<int>(pairs.size()));
    if (added) {
      pairs.push_back({lo, hi, values_size, 0});
      values_size += static_cast<std::size_t>(keyframe_blocks[static_cast<std::size_t>(lo)].tangent *
                                              keyframe_blocks[static_cast<std::size_t>(hi)].tangent);
    }
    return it->second;
  }

  bool freeBlock(int b) const { return !keyframe_blocks[static_cast<std::size_t>(b)].held; }

  void cachePoses() {
    R_w_s.resize(keyframe_blocks.size());
    p_w_s.resize(keyframe_blocks.size());
    for (std::size_t b = 0; b < keyframe_blocks.size(); ++b) {
      const double* x = keyframe_blocks[b].x;
      if (!keyframe_blocks[b].pose) continue;
      R_w_s[b] = Eigen::Quaterniond(x[6], x[3], x[4], x[5]).normalized().toRotationMatrix();
      p_w_s[b] = Vec3(x[0], x[1], x[2]);
    }
  }

  void setup(int parts);
  void buildPattern();
  bool linearize(int parts);
  bool eliminateAndSolve(double lambda, int parts, double& model_reduction);
  bool evaluateCost(int parts, double& out);
  void applyStep();
  void restore();
  [[nodiscard]] double stateNorm() const;
  [[nodiscard]] double stepNorm() const;
  // A keyframe factor's residual and its Jacobians in the tangent space of each block.
  bool evaluateKeyframeFactor(const KeyframeFactor& f, Eigen::VectorXd& r,
                              std::vector<Eigen::MatrixXd>* tangent_jacobians) const;
};

SchurProblem::SchurProblem() : impl_(std::make_unique<Impl>()) {}
SchurProblem::~SchurProblem() = default;

int SchurProblem::addPose(double* pose) {
  impl_->keyframe_blocks.push_back({pose, factors::kPoseSize, factors::kPoseTangentSize, true, false, -1});
  return static_cast<int>(impl_->keyframe_blocks.size()) - 1;
}

int SchurProblem::addVector(double* values, int size) {
  impl_->keyframe_blocks.push_back({values, size, size, false, false, -1});
  return static_cast<int>(impl_->keyframe_blocks.size()) - 1;
}

int SchurProblem::addPoint(double* p_w) {
  impl_->points.push_back({p_w, false});
  return static_cast<int>(impl_->points.size()) - 1;
}

void SchurProblem::setKeyframeBlockHeld(int block, bool held) {
  impl_->keyframe_blocks.at(static_cast<std::size_t>(block)).held = held;
}

void SchurProblem::setPointHeld(int point, bool held) {
  impl_->points.at(static_cast<std::size_t>(point)).held = held;
}

void SchurProblem::addReprojection(std::unique_ptr<factors::WorldPointReprojectionFactor> factor, int pose, int point,
                                   double cauchy_scale) {
  impl_->reprojections.push_back({std::move(factor), pose, point, cauchy_scale * cauchy_scale});
}

void SchurProblem::addKeyframeFactor(std::unique_ptr<ceres::CostFunction> factor, std::vector<int> blocks) {
  impl_->keyframe_factors.push_back({std::move(factor), std::move(blocks), {}});
}

void SchurProblem::Impl::setup(int parts) {
  dim = 0;
  for (KeyframeBlock& b : keyframe_blocks) {
    b.offset = b.held ? -1 : dim;
    if (!b.held) dim += b.tangent;
  }
  pairs.clear();
  values_size = 0;
  std::unordered_map<std::uint64_t, int> pair_index;
  diagonal_pair.assign(keyframe_blocks.size(), -1);
  for (std::size_t b = 0; b < keyframe_blocks.size(); ++b) {
    if (freeBlock(static_cast<int>(b))) {
      diagonal_pair[b] = pairOf(static_cast<int>(b), static_cast<int>(b), pair_index);
    }
  }

  // Observations by point, and within a point by pose: a counting sort, then each point's few entries sorted.
  obs_start.assign(points.size() + 1, 0);
  for (const Reprojection& r : reprojections) ++obs_start[static_cast<std::size_t>(r.point) + 1];
  for (std::size_t p = 0; p < points.size(); ++p) obs_start[p + 1] += obs_start[p];
  obs.assign(reprojections.size(), 0);
  {
    std::vector<int> fill(obs_start.begin(), obs_start.end() - 1);
    for (std::size_t i = 0; i < reprojections.size(); ++i) {
      obs[static_cast<std::size_t>(fill[static_cast<std::size_t>(reprojections[i].point)]++)] = static_cast<int>(i);
    }
  }
  obs_slot.assign(obs.size(), -1);
  slot_start.assign(points.size() + 1, 0);
  slot_pose.clear();
  point_pair_start.assign(points.size() + 1, 0);
  point_pairs.clear();
  for (std::size_t p = 0; p < points.size(); ++p) {
    const auto begin = obs.begin() + obs_start[p];
    const auto end = obs.begin() + obs_start[p + 1];
    std::sort(begin, end, [&](int a, int b) {
      return std::pair(reprojections[static_cast<std::size_t>(a)].pose, a) <
             std::pair(reprojections[static_cast<std::size_t>(b)].pose, b);
    });
    const int first_slot = static_cast<int>(slot_pose.size());
    if (!points[p].held) {
      for (int e = obs_start[p]; e < obs_start[p + 1]; ++e) {
        const int pose = reprojections[static_cast<std::size_t>(obs[static_cast<std::size_t>(e)])].pose;
        if (!freeBlock(pose)) continue;
        if (static_cast<int>(slot_pose.size()) == first_slot || slot_pose.back() != pose) slot_pose.push_back(pose);
        obs_slot[static_cast<std::size_t>(e)] = static_cast<int>(slot_pose.size()) - 1;
      }
      for (std::size_t a = static_cast<std::size_t>(first_slot); a < slot_pose.size(); ++a) {
        for (std::size_t b = a; b < slot_pose.size(); ++b) {
          point_pairs.push_back(pairOf(slot_pose[a], slot_pose[b], pair_index));
        }
      }
    }
    slot_start[p + 1] = static_cast<int>(slot_pose.size());
    point_pair_start[p + 1] = point_pairs.size();
  }
  for (KeyframeFactor& f : keyframe_factors) {
    f.pairs.clear();
    for (std::size_t i = 0; i < f.blocks.size(); ++i) {
      for (std::size_t j = i; j < f.blocks.size(); ++j) {
        const bool both_free = freeBlock(f.blocks[i]) && freeBlock(f.blocks[j]);
        f.pairs.push_back(both_free ? pairOf(f.blocks[i], f.blocks[j], pair_index) : -1);
      }
    }
  }
  buildPattern();

  // Sized only: linearize() and eliminateAndSolve() write every entry before anything reads it (zeroing tens
  // of MB here cost as much as the rest of the setup).
  C.resize(values_size);
  S.resize(values_size);
  gc.resize(dim);
  g.resize(dim);
  Hpp.resize(points.size());
  bp.resize(points.size());
  W.resize(slot_pose.size());
  Hinv.resize(points.size());
  point_diagonal.resize(points.size());
  dp.resize(points.size());
  part_values.resize(static_cast<std::size_t>(std::max(parts - 1, 0)));
  for (std::vector<double>& v : part_values) v.resize(values_size);
  part_rhs.resize(static_cast<std::size_t>(std::max(parts - 1, 0)));
  for (Eigen::VectorXd& v : part_rhs) v.resize(dim);
  part_cost.assign(static_cast<std::size_t>(parts), 0.0);
  part_failed.assign(static_cast<std::size_t>(parts), 0);
}

void SchurProblem::Impl::buildPattern() {
  // Upper triangle, column-major; every stored pair is a full dense block (CHOLMOD reads only the upper part of
  // a diagonal block). Within each column the pairs go by row.
  std::vector<std::vector<int>> by_column(keyframe_blocks.size());
  for (std::size_t p = 0; p < pairs.size(); ++p)
    by_column[static_cast<std::size_t>(pairs[p].col)].push_back(static_cast<int>(p));
  column_start.assign(static_cast<std::size_t>(dim) + 1, 0);
  std::vector<int> rows;
  for (std::size_t c = 0; c < keyframe_blocks.size(); ++c) {
    const KeyframeBlock& block = keyframe_blocks[c];
    if (block.held) continue;
    std::sort(by_column[c].begin(), by_column[c].end(), [&](int a, int b) {
      return pairs[static_cast<std::size_t>(a)].row < pairs[static_cast<std::size_t>(b)].row;
    });
    int height = 0;
    for (int p : by_column[c]) {
      pairs[static_cast<std::size_t>(p)].row_in_column = height;
      height += keyframe_blocks[static_cast<std::size_t>(pairs[static_cast<std::size_t>(p)].row)].tangent;
    }
    for (int j = 0; j < block.tangent; ++j) {
      column_start[static_cast<std::size_t>(block.offset + j + 1)] =
          column_start[static_cast<std::size_t>(block.offset + j)] + height;
      for (int p : by_column[c]) {
        const KeyframeBlock& row = keyframe_blocks[static_cast<std::size_t>(pairs[static_cast<std::size_t>(p)].row)];
        for (int i = 0; i < row.tangent; ++i) rows.push_back(row.offset + i);
      }
    }
  }
  reduced = SparseMatrix(dim, dim);
  reduced.resizeNonZeros(static_cast<Eigen::Index>(rows.size()));
  std::copy(column_start.begin(), column_start.end(), reduced.outerIndexPtr());
  std::copy(rows.begin(), rows.end(), reduced.innerIndexPtr());
  std::fill(reduced.valuePtr(), reduced.valuePtr() + rows.size(), 0.0);
  cholmod.reset();
  if (dim > 0) {
    cholmod = std::make_unique<Eigen::CholmodDecomposition<SparseMatrix, Eigen::Upper>>();
    cholmod->analyzePattern(reduced);
  }
}

bool SchurProblem::Impl::evaluateKeyframeFactor(const KeyframeFactor& f, Eigen::VectorXd& r,
                                                std::vector<Eigen::MatrixXd>* tangent_jacobians) const {
  const int rows = f.factor->num_residuals();
  r.resize(rows);
  std::vector<const double*> parameters;
  std::vector<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> ambient(f.blocks.size());
  std::vector<double*> jacobians(f.blocks.size(), nullptr);
  for (std::size_t i = 0; i < f.blocks.size(); ++i) {
    const KeyframeBlock& b = keyframe_blocks[static_cast<std::size_t>(f.blocks[i])];
    parameters.push_back(b.x);
    if (tangent_jacobians != nullptr && !b.held) {
      ambient[i].resize(rows, b.size);
      jacobians[i] = ambient[i].data();
    }
  }
  if (!f.factor->Evaluate(parameters.data(), r.data(), tangent_jacobians != nullptr ? jacobians.data() : nullptr)) {
    return false;
  }
  if (tangent_jacobians == nullptr) return true;
  tangent_jacobians->assign(f.blocks.size(), Eigen::MatrixXd());
  const factors::PoseManifold manifold;
  for (std::size_t i = 0; i < f.blocks.size(); ++i) {
    const KeyframeBlock& b = keyframe_blocks[static_cast<std::size_t>(f.blocks[i])];
    if (b.held) continue;
    if (b.pose) {
      Eigen::Matrix<double, factors::kPoseSize, factors::kPoseTangentSize, Eigen::RowMajor> lift;
      manifold.PlusJacobian(b.x, lift.data());
      (*tangent_jacobians)[i] = ambient[i] * lift;
    } else {
      (*tangent_jacobians)[i] = ambient[i];
    }
  }
  return true;
}

bool SchurProblem::Impl::linearize(int parts) {
  std::fill(C.begin(), C.end(), 0.0);
  gc.setZero();
  for (std::vector<double>& v : part_values) std::fill(v.begin(), v.end(), 0.0);
  for (Eigen::VectorXd& v : part_rhs) v.setZero();
  std::fill(part_cost.begin(), part_cost.end(), 0.0);
  std::fill(part_failed.begin(), part_failed.end(), 0);
  cachePoses();
  splitOver(parts, points.size(), [&](int part, std::size_t begin, std::size_t end) {
    double* values = part == 0 ? C.data() : part_values[static_cast<std::size_t>(part - 1)].data();
    Eigen::VectorXd& rhs = part == 0 ? gc : part_rhs[static_cast<std::size_t>(part - 1)];
    double cost = 0.0;
    for (std::size_t p = begin; p < end; ++p) {
      const bool point_free = !points[p].held;
      Mat33 H = Mat33::Zero();
      Vec3 b = Vec3::Zero();
      for (int s = slot_start[p]; s < slot_start[p + 1]; ++s) W[static_cast<std::size_t>(s)].setZero();
      for (int e = obs_start[p]; e < obs_start[p + 1]; ++e) {
        const Reprojection& o = reprojections[static_cast<std::size_t>(obs[static_cast<std::size_t>(e)])];
        const KeyframeBlock& pose = keyframe_blocks[static_cast<std::size_t>(o.pose)];
        Eigen::Vector2d r;
        Eigen::Matrix<double, 2, 6> J_pose;
        Eigen::Matrix<double, 2, 3> J_point;
        if (!o.factor->evaluateTangent(R_w_s[static_cast<std::size_t>(o.pose)], p_w_s[static_cast<std::size_t>(o.pose)],
                                       points[p].x, r, pose.held ? nullptr : &J_pose,
                                       point_free ? &J_point : nullptr)) {
          part_failed[static_cast<std::size_t>(part)] = 1;
          continue;
        }
        const Robust robust = cauchy(r.squaredNorm(), o.b);
        cost += 0.5 * robust.rho;
        r *= robust.weight;
        if (point_free) {
          J_point *= robust.weight;
          H.noalias() += J_point.transpose() * J_point;
          b.noalias() += J_point.transpose() * r;
        }
        if (pose.held) continue;
        J_pose *= robust.weight;
        const Pair& diagonal = pairs[static_cast<std::size_t>(diagonal_pair[static_cast<std::size_t>(o.pose)])];
        Eigen::Map<Mat66>(values + diagonal.value).noalias() += J_pose.transpose() * J_pose;
        rhs.segment<6>(pose.offset).noalias() += J_pose.transpose() * r;
        const int slot = obs_slot[static_cast<std::size_t>(e)];
        if (slot >= 0) W[static_cast<std::size_t>(slot)].noalias() += J_pose.transpose() * J_point;
      }
      Hpp[p] = H;
      bp[p] = b;
    }
    part_cost[static_cast<std::size_t>(part)] = cost;
  });
  cost_at = 0.0;
  for (std::size_t part = 0; part < part_cost.size(); ++part) {
    if (part_failed[part] != 0) return false;
    cost_at += part_cost[part];
  }
  for (std::size_t part = 0; part < part_values.size(); ++part) {
    for (std::size_t k = 0; k < values_size; ++k) C[k] += part_values[part][k];
    gc += part_rhs[part];
  }
  Eigen::VectorXd r;
  std::vector<Eigen::MatrixXd> J;
  for (const KeyframeFactor& f : keyframe_factors) {
    if (!evaluateKeyframeFactor(f, r, &J)) return false;
    cost_at += 0.5 * r.squaredNorm();
    std::size_t k = 0;
    for (std::size_t i = 0; i < f.blocks.size(); ++i) {
      const KeyframeBlock& bi = keyframe_blocks[static_cast<std::size_t>(f.blocks[i])];
      if (!bi.held) gc.segment(bi.offset, bi.tangent).noalias() += J[i].transpose() * r;
      for (std::size_t j = i; j < f.blocks.size(); ++j, ++k) {
        if (f.pairs[k] < 0) continue;
        const Pair& pair = pairs[static_cast<std::size_t>(f.pairs[k])];
        const KeyframeBlock& row = keyframe_blocks[static_cast<std::size_t>(pair.row)];
        const KeyframeBlock& col = keyframe_blocks[static_cast<std::size_t>(pair.col)];
        Eigen::Map<Eigen::MatrixXd> block(C.data() + pair.value, row.tangent, col.tangent);
        // The pair's rows are the lower-indexed block; a factor may list its blocks in either order.
        const bool i_is_row = f.blocks[i] == pair.row;
        const Eigen::MatrixXd& J_row = i_is_row ? J[i] : J[j];
        const Eigen::MatrixXd& J_col = i_is_row ? J[j] : J[i];
        if (i != j && f.blocks[i] == f.blocks[j]) {
          block.noalias() += J_row.transpose() * J_col + J_col.transpose() * J_row;  // one block listed twice
        } else {
          block.noalias() += J_row.transpose() * J_col;
        }
      }
    }
  }
  return std::isfinite(cost_at);
}

bool SchurProblem::Impl::eliminateAndSolve(double lambda, int parts, double& model_reduction) {
  std::copy(C.begin(), C.end(), S.begin());
  g = gc;
  keyframe_diagonal.resize(dim);
  for (std::size_t b = 0; b < keyframe_blocks.size(); ++b) {
    const KeyframeBlock& block = keyframe_blocks[b];
    if (block.held) continue;
    double* values = S.data() + pairs[static_cast<std::size_t>(diagonal_pair[b])].value;
    for (int k = 0; k < block.tangent; ++k) {
      const double d = clampDiagonal(values[k * block.tangent + k]);
      keyframe_diagonal[block.offset + k] = d;
      values[k * block.tangent + k] += lambda * d;
    }
  }
  for (std::vector<double>& v : part_values) std::fill(v.begin(), v.end(), 0.0);
  for (Eigen::VectorXd& v : part_rhs) v.setZero();
  // Eliminate every point: S -= W Hpp^-1 W^T, g -= W Hpp^-1 b_p.
  splitOver(parts, points.size(), [&](int part, std::size_t begin, std::size_t end) {
    double* values = part == 0 ? S.data() : part_values[static_cast<std::size_t>(part - 1)].data();
    Eigen::VectorXd& rhs = part == 0 ? g : part_rhs[static_cast<std::size_t>(part - 1)];
    std::vector<Mat63> V;
    for (std::size_t p = begin; p < end; ++p) {
      if (points[p].held) continue;
      Mat33 H = Hpp[p];
      for (int k = 0; k < 3; ++k) {
        point_diagonal[p][k] = clampDiagonal(H(k, k));
        H(k, k) += lambda * point_diagonal[p][k];
      }
      Hinv[p] = H.inverse();
      const int first = slot_start[p];
      const int count = slot_start[p + 1] - first;
      V.resize(static_cast<std::size_t>(count));
      for (int a = 0; a < count; ++a) {
        const Mat63& Wa = W[static_cast<std::size_t>(first + a)];
        V[static_cast<std::size_t>(a)].noalias() = Wa * Hinv[p];
        const int offset =
            keyframe_blocks[static_cast<std::size_t>(slot_pose[static_cast<std::size_t>(first + a)])].offset;
        rhs.segment<6>(offset).noalias() -= V[static_cast<std::size_t>(a)] * bp[p];
      }
      std::size_t k = point_pair_start[p];
      for (int a = 0; a < count; ++a) {
        for (int b = a; b < count; ++b, ++k) {
          const Pair& pair = pairs[static_cast<std::size_t>(point_pairs[k])];
          Eigen::Map<Mat66>(values + pair.value).noalias() -=
              V[static_cast<std::size_t>(a)] * W[static_cast<std::size_t>(first + b)].transpose();
        }
      }
    }
  });
  for (std::size_t part = 0; part < part_values.size(); ++part) {
    for (std::size_t k = 0; k < values_size; ++k) S[k] += part_values[part][k];
    g += part_rhs[part];
  }

  Eigen::VectorXd step_c = Eigen::VectorXd::Zero(dim);
  if (dim > 0) {
    double* csc = reduced.valuePtr();
    for (const Pair& pair : pairs) {
      const int height = keyframe_blocks[static_cast<std::size_t>(pair.row)].tangent;
      const KeyframeBlock& col = keyframe_blocks[static_cast<std::size_t>(pair.col)];
      for (int j = 0; j < col.tangent; ++j) {
        std::copy_n(S.data() + pair.value + static_cast<std::size_t>(j * height), height,
                    csc + column_start[static_cast<std::size_t>(col.offset + j)] + pair.row_in_column);
      }
    }
    cholmod->factorize(reduced);
    if (cholmod->info() != Eigen::Success) return false;
    step_c = cholmod->solve(-g);
    if (cholmod->info() != Eigen::Success || !step_c.allFinite()) return false;
  }
  dc = step_c;
  // Back-substitution: each point's step given the keyframes' step.
  splitOver(parts, points.size(), [&](int /*part*/, std::size_t begin, std::size_t end) {
    for (std::size_t p = begin; p < end; ++p) {
      if (points[p].held) continue;
      Vec3 rhs = -bp[p];
      for (int s = slot_start[p]; s < slot_start[p + 1]; ++s) {
        const int offset = keyframe_blocks[static_cast<std::size_t>(slot_pose[static_cast<std::size_t>(s)])].offset;
        rhs.noalias() -= W[static_cast<std::size_t>(s)].transpose() * dc.segment<6>(offset);
      }
      dp[p] = Hinv[p] * rhs;
    }
  });
  // The model's decrease at the damped step: (-g^T d + lambda d^T D d) / 2 over every free parameter.
  double reduction = -gc.dot(dc) + lambda * (keyframe_diagonal.array() * dc.array().square()).sum();
  for (std::size_t p = 0; p < points.size(); ++p) {
    if (points[p].held) continue;
    reduction += -bp[p].dot(dp[p]) + lambda * (point_diagonal[p].array() * dp[p].array().square()).sum();
  }
  model_reduction = 0.5 * reduction;
  return std::isfinite(model_reduction);
}

bool SchurProblem::Impl::evaluateCost(int parts, double& out) {
  cachePoses();
  std::vector<double> costs(static_cast<std::size_t>(std::max(parts, 1)), 0.0);
  std::vector<std::uint8_t> failed(costs.size(), 0);
  splitOver(static_cast<int>(costs.size()), reprojections.size(), [&](int part, std::size_t begin, std::size_t end) {
    double cost = 0.0;
    for (std::size_t i = begin; i < end; ++i) {
      const Reprojection& o = reprojections[i];
      Eigen::Vector2d r;
      if (!o.factor->evaluateTangent(R_w_s[static_cast<std::size_t>(o.pose)], p_w_s[static_cast<std::size_t>(o.pose)],
                                     points[static_cast<std::size_t>(o.point)].x, r, nullptr, nullptr)) {
        failed[static_cast<std::size_t>(part)] = 1;
        return;
      }
      cost += 0.5 * cauchy(r.squaredNorm(), o.b).rho;
    }
    costs[static_cast<std::size_t>(part)] = cost;
  });
  out = 0.0;
  for (std::size_t part = 0; part < costs.size(); ++part) {
    if (failed[part] != 0) return false;
    out += costs[part];
  }
  Eigen::VectorXd r;
  for (const KeyframeFactor& f : keyframe_factors) {
    if (!evaluateKeyframeFactor(f, r, nullptr)) return false;
    out += 0.5 * r.squaredNorm();
  }
  return std::isfinite(out);
}

void SchurProblem::Impl::applyStep() {
  backup.clear();
  const factors::PoseManifold manifold;
  for (const KeyframeBlock& b : keyframe_blocks) {
    if (b.held) continue;
    backup.insert(backup.end(), b.x, b.x + b.size);
    if (b.pose) {
      double moved[factors::kPoseSize];
      manifold.Plus(b.x, dc.data() + b.offset, moved);
      std::copy_n(moved, factors::kPoseSize, b.x);
    } else {
      for (int k = 0; k < b.size; ++k) b.x[k] += dc[b.offset + k];
    }
  }
  for (std::size_t p = 0; p < points.size(); ++p) {
    if (points[p].held) continue;
    backup.insert(backup.end(), points[p].x, points[p].x + 3);
    for (int k = 0; k < 3; ++k) points[p].x[k] += dp[p][k];
  }
}

void SchurProblem::Impl::restore() {
  std::size_t k = 0;
  for (const KeyframeBlock& b : keyframe_blocks) {
    if (b.held) continue;
    std::copy_n(backup.data() + k, b.size, b.x);
    k += static_cast<std::size_t>(b.size);
  }
  for (const PointBlock& p : points) {
    if (p.held) continue;
    std::copy_n(backup.data() + k, 3, p.x);
    k += 3;
  }
}

double SchurProblem::Impl::stateNorm() const {
  double sum = 0.0;
  for (const KeyframeBlock& b : keyframe_blocks) {
    if (!b.held) sum += Eigen::Map<const Eigen::VectorXd>(b.x, b.size).squaredNorm();
  }
  for (const PointBlock& p : points) {
    if (!p.held) sum += Eigen::Map<const Vec3>(p.x).squaredNorm();
  }
  return std::sqrt(sum);
}

double SchurProblem::Impl::stepNorm() const {
  double sum = dc.squaredNorm();
  for (std::size_t p = 0; p < points.size(); ++p) {
    if (!points[p].held) sum += dp[p].squaredNorm();
  }
  return std::sqrt(sum);
}

bool SchurProblem::cost(double& out, int threads) {
  return impl_->evaluateCost(threads, out);
}

Eigen::VectorXd SchurProblem::gradient() {
  Impl& m = *impl_;
  m.setup(1);
  if (!m.linearize(1)) return {};
  int free_points = 0;
  for (const Impl::PointBlock& p : m.points) free_points += p.held ? 0 : 1;
  Eigen::VectorXd gradient(m.dim + 3 * free_points);
  gradient.head(m.dim) = m.gc;
  int k = m.dim;
  for (std::size_t p = 0; p < m.points.size(); ++p) {
    if (m.points[p].held) continue;
    gradient.segment<3>(k) = m.bp[p];
    k += 3;
  }
  return gradient;
}

SchurSolverSummary SchurProblem::solve(const SchurSolverOptions& options) {
  Impl& m = *impl_;
  SchurSolverSummary summary;
  const auto start = Clock::now();
  const int parts = std::max(options.threads, 1);
  m.setup(parts);
  summary.setup_s = secondsSince(start);

  auto t = Clock::now();
  bool ok = m.linearize(parts);
  summary.linearize_s += secondsSince(t);
  summary.initial_cost = summary.final_cost = m.cost_at;
  if (!ok) return summary;
  double radius = kInitialRadius;
  double decrease_factor = 2.0;
  double last_step_s = 0.0;
  while (summary.iterations < options.max_iterations) {
    if (options.cancel != nullptr && options.cancel->load(std::memory_order_relaxed)) {
      summary.cancelled = true;
      break;
    }
    if (secondsSince(start) > options.max_time_s) break;
    const auto step_start = Clock::now();
    if (options.deadline && summary.iterations > 0 &&
        step_start + std::chrono::duration<double>(last_step_s) > *options.deadline) {
      summary.deadline_reached = true;
      break;
    }
    ++summary.iterations;
    t = step_start;
    double model_reduction = 0.0;
    const bool solved = m.eliminateAndSolve(1.0 / radius, parts, model_reduction);
    summary.linear_solver_s += secondsSince(t);
    if (solved && model_reduction > 0.0) {
      // A step too small to change anything: converged.
      if (m.stepNorm() <= kParameterTolerance * (m.stateNorm() + kParameterTolerance)) break;
      m.applyStep();
      t = Clock::now();
      double new_cost = 0.0;
      const bool evaluated = m.evaluateCost(parts, new_cost);
      summary.evaluate_s += secondsSince(t);
      const double ratio = evaluated ? (m.cost_at - new_cost) / model_reduction : -1.0;
      if (ratio > kMinRelativeDecrease) {
        radius = std::min(kMaxRadius, radius / std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * ratio - 1.0, 3)));
        decrease_factor = 2.0;
        summary.final_cost = new_cost;
        summary.accepted.push_back({secondsSince(start), new_cost});
        if (std::abs(m.cost_at - new_cost) <= options.function_tolerance * m.cost_at) break;  // converged
        if (summary.iterations == options.max_iterations) break;  // no step left to linearise for
        t = Clock::now();
        ok = m.linearize(parts);
        summary.linearize_s += secondsSince(t);
        if (!ok) break;
        last_step_s = secondsSince(step_start);
        continue;
      }
      m.restore();
    }
    last_step_s = secondsSince(step_start);
    radius /= decrease_factor;
    decrease_factor *= 2.0;
    if (radius < kMinRadius) break;
  }
  return summary;
}

}  // namespace cvislam::server::backend
