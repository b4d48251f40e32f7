// Residual and Jacobian buffers sized once for a ceres::CostFunction, so that a loop can call Evaluate()
// repeatedly on fixed parameter blocks (the benchmarks and the allocation-counting test do).
#pragma once

#include <utility>
#include <vector>

#include <ceres/cost_function.h>

namespace cvislam::test {

class CostEvaluation {
 public:
  CostEvaluation(const ceres::CostFunction& cost, std::vector<const double*> blocks)
      : cost_(cost), blocks_(std::move(blocks)), residuals_(static_cast<std::size_t>(cost.num_residuals())) {
    for (std::size_t i = 0; i < blocks_.size(); ++i) {
      storage_.emplace_back(static_cast<std::size_t>(cost.num_residuals() * cost.parameter_block_sizes()[i]));
    }
    for (auto& s : storage_) jacobians_.push_back(s.data());
  }

  // Evaluates the residuals and every Jacobian into the buffers.
  bool evaluate() { return cost_.Evaluate(blocks_.data(), residuals_.data(), jacobians_.data()); }

  [[nodiscard]] const double* firstJacobian() const { return jacobians_.front(); }

 private:
  const ceres::CostFunction& cost_;
  std::vector<const double*> blocks_;
  std::vector<double> residuals_;
  std::vector<std::vector<double>> storage_;
  std::vector<double*> jacobians_;
};

}  // namespace cvislam::test
