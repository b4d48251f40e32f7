// SO(3), SE(3) and Sim(3) on Eigen: the one Lie-group header of cvislam.
//
// CONVENTIONS (read these before using anything below)
//
// * Quaternions are Hamilton (i*j = k), stored as Eigen::Quaternion (coefficients x, y, z, w in memory;
//   files and constructors in this project say which order they use). q and -q are the same rotation.
// * Frames are in names: T_a_b maps coordinates in frame b to frame a, p_a = T_a_b * p_b.
//   Composition chains frames: T_a_c = T_a_b * T_b_c.
// * Tangent vectors, translation part first (as Sophus and Barfoot):
//     SO3:  phi                      (3)   rotation vector, |phi| = angle in radians
//     SE3:  xi   = [rho; phi]        (6)
//     Sim3: zeta = [rho; phi; sigma] (7)   sigma = log(scale)
//   hat() maps them to the Lie algebra, vee() back. exp() / log() map between algebra and group.
// * Perturbations. The RIGHT perturbation X (+) d = X * exp(d) is the default everywhere in cvislam
//   (optimisation states, manifolds, Jacobians of factors); the left one, exp(d) * X, is available.
// * Jacobians of exp, for a tangent vector x and a small d:
//     exp(x + d) ~= exp(x) * exp(Jr(x) d)        rightJacobian(x)
//     exp(x + d) ~= exp(Jl(x) d) * exp(x)        leftJacobian(x),  Jl(x) = Jr(-x) = Ad(exp(x)) Jr(x)
//   and of log, for a group element X = exp(x):
//     log(X * exp(d)) ~= x + Jr(x)^-1 d          rightJacobianInverse(x)
//     log(exp(d) * X) ~= x + Jl(x)^-1 d          leftJacobianInverse(x)
// * Adjoint: X * exp(d) * X^-1 = exp(Ad(X) d), so X * exp(d) = exp(Ad(X) d) * X.
//
// SO3 and SE3 use closed forms (Barfoot, "State Estimation for Robotics", 2017, sections 7.1.4 and 7.1.5),
// with their Taylor series below 1 rad (where the closed forms cancel). log() returns angles in [0, pi]. Sim3 exp/log
// are closed form; the Sim3 Jacobians are the power series sum_k (+-ad)^k / (k+1)! of the 7x7 algebra adjoint, summed
// to machine precision (they serve the server's pose graph, not the agent's hot path), and their inverses
// a 7x7 LU solve. Every Jacobian here is tested against numeric differentiation in
// test/common/geometry/lie_test.cpp, at random points, near zero and near pi.
//
// The classes are templated on the scalar so that Ceres Jets can flow through them.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/LU>
#include <cmath>
#include <limits>

namespace cvislam::geometry {

template <typename Scalar>
using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
template <typename Scalar>
using Mat3 = Eigen::Matrix<Scalar, 3, 3>;

// [v]x: the skew-symmetric matrix with [v]x w = v x w.
template <typename Scalar>
Mat3<Scalar> hatSO3(const Vec3<Scalar>& v) {
  Mat3<Scalar> m;
  m << Scalar(0), -v.z(), v.y(),  //
      v.z(), Scalar(0), -v.x(),   //
      -v.y(), v.x(), Scalar(0);
  return m;
}

template <typename Scalar>
Vec3<Scalar> veeSO3(const Mat3<Scalar>& m) {
  return Vec3<Scalar>(m(2, 1), m(0, 2), m(1, 0));
}

namespace detail {

// Below this angle the Jacobian coefficients are evaluated from their Taylor series. The closed forms
// cancel catastrophically near zero (the error of (t - sin t)/t^3 grows like eps/t^2, that of
// (t - sin t - t^3/6)/t^5 like eps/t^4); at t = 1 both the closed forms and the series truncated below
// are accurate to ~1e-14.
template <typename Scalar>
Scalar seriesAngle() {
  return Scalar(1);
}

// sum_{k=0..10} (-1)^k x^k / (2k + m)!, with x = theta^2. For m = 1, 2, 3, 4, 5 this is sin(t)/t,
// (1 - cos t)/t^2, (t - sin t)/t^3, (t^2/2 + cos t - 1)/t^4 and -(t - sin t - t^3/6)/t^5.
template <typename Scalar>
Scalar alternatingFactorialSeries(const Scalar& x, int m) {
  constexpr int kTerms = 11;
  // Horner from the last term: c_k = 1/(2k+m)!, c_{k}/c_{k-1} = 1/((2k+m)(2k+m-1)).
  Scalar sum(1);
  for (int k = kTerms - 1; k >= 1; --k) {
    sum = Scalar(1) - x * sum / Scalar((2 * k + m) * (2 * k + m - 1));
  }
  double first = 1.0;  // 1 / m!
  for (int i = 2; i <= m; ++i) first /= i;
  return Scalar(first) * sum;
}

// a(theta) = (1 - cos theta) / theta^2,  b(theta) = (theta - sin theta) / theta^3
template <typename Scalar>
void so3JacobianCoefficients(const Scalar& theta, Scalar& a, Scalar& b) {
  using std::cos;
  using std::sin;
  const Scalar theta2 = theta * theta;
  if (theta < seriesAngle<Scalar>()) {
    a = alternatingFactorialSeries(theta2, 2);
    b = alternatingFactorialSeries(theta2, 3);
  } else {
    a = (Scalar(1) - cos(theta)) / theta2;
    b = (theta - sin(theta)) / (theta2 * theta);
  }
}

// c(theta) = 1/theta^2 - cot(theta/2) / (2 theta) = sum_n |B_2n| / (2n)! theta^(2n-2) (Bernoulli numbers);
// the series converges for theta < 2 pi and is used below seriesAngle().
template <typename Scalar>
Scalar so3InverseJacobianCoefficient(const Scalar& theta) {
  using std::tan;
  const Scalar theta2 = theta * theta;
  if (theta < seriesAngle<Scalar>()) {
    static constexpr double kCoefficients[] = {1.0 / 12.0,          1.0 / 720.0,
                                               1.0 / 30240.0,       1.0 / 1209600.0,
                                               1.0 / 47900160.0,    691.0 / 1307674368000.0,
                                               1.0 / 74724249600.0, 3617.0 / 10670622842880000.0};
    Scalar c(0);
    for (int k = 7; k >= 0; --k) c = Scalar(kCoefficients[k]) + theta2 * c;
    return c;
  }
  return Scalar(1) / theta2 - Scalar(1) / (Scalar(2) * theta * tan(theta / Scalar(2)));
}

}  // namespace detail

// ------------------------------------------------------------------------------------------------ SO3
template <typename Scalar_>
class SO3 {
 public:
  using Scalar = Scalar_;
  using Quaternion = Eigen::Quaternion<Scalar>;
  using Tangent = Vec3<Scalar>;
  using Matrix3 = Mat3<Scalar>;
  using Adjoint = Mat3<Scalar>;
  static constexpr int kDoF = 3;

  SO3() : q_(Quaternion::Identity()) {}
  // The quaternion is normalised; it must not be zero.
  explicit SO3(const Quaternion& q) : q_(q.normalized()) {}
  // The matrix must be a rotation (orthonormal, det +1); it is projected to the nearest quaternion.
  explicit SO3(const Matrix3& R) : q_(Quaternion(R).normalized()) {}

  static SO3 identity() { return SO3(); }

  // exp(phi) via the half-angle quaternion.
  static SO3 exp(const Tangent& phi) {
    using std::cos;
    using std::sin;
    using std::sqrt;
    const Scalar theta2 = phi.squaredNorm();
    Scalar w;
    Scalar k;                     // sin(theta/2) / theta
    if (theta2 < Scalar(1e-6)) {  // Taylor: truncation error ~theta^6
      w = Scalar(1) - theta2 / Scalar(8) + theta2 * theta2 / Scalar(384);
      k = Scalar(0.5) - theta2 / Scalar(48) + theta2 * theta2 / Scalar(3840);
    } else {
      const Scalar theta = sqrt(theta2);
      w = cos(theta / Scalar(2));
      k = sin(theta / Scalar(2)) / theta;
    }
    SO3 out;
    out.q_ = Quaternion(w, k * phi.x(), k * phi.y(), k * phi.z());
    return out;
  }

  // log(R) with the angle in [0, pi]; stable near 0 and near pi (atan2 on the quaternion).
  [[nodiscard]] Tangent log() const {
    using std::atan2;
    using std::sqrt;
    // q and -q are the same rotation; w >= 0 picks the angle in [0, pi].
    const Scalar sign = q_.w() < Scalar(0) ? Scalar(-1) : Scalar(1);
    const Scalar w = sign * q_.w();
    const Tangent v = sign * q_.vec();
    const Scalar n2 = v.squaredNorm();
    if (n2 < Scalar(1e-16)) {
      // theta = 2 atan(n / w) ~ 2 n / w (1 - n^2 / (3 w^2)); here w ~ 1.
      const Scalar w2 = w * w;
      return Scalar(2) / w * (Scalar(1) - n2 / (Scalar(3) * w2)) * v;
    }
    const Scalar n = sqrt(n2);
    const Scalar theta = Scalar(2) * atan2(n, w);
    return (theta / n) * v;
  }

  [[nodiscard]] SO3 inverse() const {
    SO3 out;
    out.q_ = q_.conjugate();
    return out;
  }

  SO3 operator*(const SO3& other) const {
    SO3 out;
    out.q_ = (q_ * other.q_).normalized();
    return out;
  }
  SO3& operator*=(const SO3& other) { return *this = *this * other; }

  // Rotates a point or vector.
  Tangent operator*(const Tangent& p) const { return q_ * p; }

  [[nodiscard]] Matrix3 matrix() const { return q_.toRotationMatrix(); }
  [[nodiscard]] const Quaternion& quaternion() const { return q_; }
  // Ad(R) = R for SO3.
  [[nodiscard]] Adjoint adjoint() const { return matrix(); }

  static Matrix3 hat(const Tangent& phi) { return hatSO3(phi); }
  static Tangent vee(const Matrix3& m) { return veeSO3(m); }

  // Jr(phi) = I - a [phi]x + b [phi]x^2,  a = (1 - cos t)/t^2, b = (t - sin t)/t^3.
  static Matrix3 rightJacobian(const Tangent& phi) {
    Scalar a;
    Scalar b;
    detail::so3JacobianCoefficients(phi.norm(), a, b);
    const Matrix3 Phi = hatSO3(phi);
    return Matrix3::Identity() - a * Phi + b * Phi * Phi;
  }
  static Matrix3 leftJacobian(const Tangent& phi) { return rightJacobian(-phi); }

  // Jr(phi)^-1 = I + 1/2 [phi]x + c [phi]x^2,  c = 1/t^2 - cot(t/2) / (2 t)  (finite at t = pi).
  static Matrix3 rightJacobianInverse(const Tangent& phi) {
    const Scalar c = detail::so3InverseJacobianCoefficient(phi.norm());
    const Matrix3 Phi = hatSO3(phi);
    return Matrix3::Identity() + Scalar(0.5) * Phi + c * Phi * Phi;
  }
  static Matrix3 leftJacobianInverse(const Tangent& phi) { return rightJacobianInverse(-phi); }

  template <typename NewScalar>
  SO3<NewScalar> cast() const {
    return SO3<NewScalar>(q_.template cast<NewScalar>());
  }

 private:
  Quaternion q_;
};

// ------------------------------------------------------------------------------------------------ SE3
template <typename Scalar_>
class SE3 {
 public:
  using Scalar = Scalar_;
  using Tangent = Eigen::Matrix<Scalar, 6, 1>;
  using Adjoint = Eigen::Matrix<Scalar, 6, 6>;
  using Matrix4 = Eigen::Matrix<Scalar, 4, 4>;
  using Point = Vec3<Scalar>;
  static constexpr int kDoF = 6;

  SE3() : t_(Point::Zero()) {}
  SE3(const SO3<Scalar>& R, const Point& t) : R_(R), t_(t) {}
  SE3(const Eigen::Quaternion<Scalar>& q, const Point& t) : R_(q), t_(t) {}
  // From a 4x4 homogeneous matrix whose top-left 3x3 block is a rotation.
  explicit SE3(const Matrix4& T)
      : R_(Mat3<Scalar>(T.template topLeftCorner<3, 3>())), t_(T.template topRightCorner<3, 1>()) {}

  static SE3 identity() { return SE3(); }

  // exp([rho; phi]) = (exp(phi), Jl(phi) rho).
  static SE3 exp(const Tangent& xi) {
    const Point phi = xi.template tail<3>();
    return SE3(SO3<Scalar>::exp(phi), SO3<Scalar>::leftJacobian(phi) * xi.template head<3>());
  }

  [[nodiscard]] Tangent log() const {
    const Point phi = R_.log();
    Tangent xi;
    xi.template head<3>() = SO3<Scalar>::leftJacobianInverse(phi) * t_;
    xi.template tail<3>() = phi;
    return xi;
  }

  [[nodiscard]] SE3 inverse() const {
    const SO3<Scalar> R_inv = R_.inverse();
    return SE3(R_inv, -(R_inv * t_));
  }

  SE3 operator*(const SE3& other) const { return SE3(R_ * other.R_, R_ * other.t_ + t_); }
  SE3& operator*=(const SE3& other) { return *this = *this * other; }
  // Transforms a point: p_a = T_a_b * p_b.
  Point operator*(const Point& p) const { return R_ * p + t_; }

  [[nodiscard]] const SO3<Scalar>& so3() const { return R_; }
  [[nodiscard]] SO3<Scalar>& so3() { return R_; }
  [[nodiscard]] const Point& translation() const { return t_; }
  [[nodiscard]] Point& translation() { return t_; }
  [[nodiscard]] Mat3<Scalar> rotationMatrix() const { return R_.matrix(); }
  [[nodiscard]] const Eigen::Quaternion<Scalar>& quaternion() const { return R_.quaternion(); }

  [[nodiscard]] Matrix4 matrix() const {
    Matrix4 T = Matrix4::Identity();
    T.template topLeftCorner<3, 3>() = R_.matrix();
    T.template topRightCorner<3, 1>() = t_;
    return T;
  }

  // Ad(T) = [R, [t]x R; 0, R].
  [[nodiscard]] Adjoint adjoint() const {
    const Mat3<Scalar> R = R_.matrix();
    Adjoint Ad = Adjoint::Zero();
    Ad.template topLeftCorner<3, 3>() = R;
    Ad.template topRightCorner<3, 3>() = hatSO3(t_) * R;
    Ad.template bottomRightCorner<3, 3>() = R;
    return Ad;
  }

  static Matrix4 hat(const Tangent& xi) {
    Matrix4 m = Matrix4::Zero();
    m.template topLeftCorner<3, 3>() = hatSO3<Scalar>(xi.template tail<3>());
    m.template topRightCorner<3, 1>() = xi.template head<3>();
    return m;
  }
  static Tangent vee(const Matrix4& m) {
    Tangent xi;
    xi.template head<3>() = m.template topRightCorner<3, 1>();
    xi.template tail<3>() = veeSO3<Scalar>(m.template topLeftCorner<3, 3>());
    return xi;
  }

  // The 6x6 algebra adjoint ad(xi) = [[phi]x, [rho]x; 0, [phi]x], so that hat(ad(x) y) = [hat(x), hat(y)].
  static Adjoint ad(const Tangent& xi) {
    Adjoint a = Adjoint::Zero();
    a.template topLeftCorner<3, 3>() = hatSO3<Scalar>(xi.template tail<3>());
    a.template topRightCorner<3, 3>() = hatSO3<Scalar>(xi.template head<3>());
    a.template bottomRightCorner<3, 3>() = hatSO3<Scalar>(xi.template tail<3>());
    return a;
  }

  // Jl(xi) = [Jl(phi), Q(rho, phi); 0, Jl(phi)]   (Barfoot eq. 7.85-7.86).
  static Adjoint leftJacobian(const Tangent& xi) {
    const Point phi = xi.template tail<3>();
    const Mat3<Scalar> Jl = SO3<Scalar>::leftJacobian(phi);
    Adjoint J = Adjoint::Zero();
    J.template topLeftCorner<3, 3>() = Jl;
    J.template topRightCorner<3, 3>() = leftQ(xi.template head<3>(), phi);
    J.template bottomRightCorner<3, 3>() = Jl;
    return J;
  }
  static Adjoint rightJacobian(const Tangent& xi) { return leftJacobian(-xi); }

  // Jl(xi)^-1 = [Jl^-1, -Jl^-1 Q Jl^-1; 0, Jl^-1].
  static Adjoint leftJacobianInverse(const Tangent& xi) {
    const Point phi = xi.template tail<3>();
    const Mat3<Scalar> Jl_inv = SO3<Scalar>::leftJacobianInverse(phi);
    Adjoint J = Adjoint::Zero();
    J.template topLeftCorner<3, 3>() = Jl_inv;
    J.template topRightCorner<3, 3>() = -Jl_inv * leftQ(xi.template head<3>(), phi) * Jl_inv;
    J.template bottomRightCorner<3, 3>() = Jl_inv;
    return J;
  }
  static Adjoint rightJacobianInverse(const Tangent& xi) { return leftJacobianInverse(-xi); }

  template <typename NewScalar>
  SE3<NewScalar> cast() const {
    return SE3<NewScalar>(R_.template cast<NewScalar>(), t_.template cast<NewScalar>());
  }

 private:
  // Barfoot's Q(rho, phi): the coupling block of the SE3 left Jacobian.
  static Mat3<Scalar> leftQ(const Point& rho, const Point& phi) {
    using std::cos;
    using std::sin;
    const Scalar theta = phi.norm();
    const Scalar theta2 = theta * theta;
    Scalar c1;  // (t - sin t) / t^3
    Scalar c2;  // (t^2/2 + cos t - 1) / t^4
    Scalar c3;  // (t - sin t - t^3/6) / t^5
    if (theta < detail::seriesAngle<Scalar>()) {
      c1 = detail::alternatingFactorialSeries(theta2, 3);
      c2 = detail::alternatingFactorialSeries(theta2, 4);
      c3 = -detail::alternatingFactorialSeries(theta2, 5);
    } else {
      const Scalar s = sin(theta);
      const Scalar c = cos(theta);
      c1 = (theta - s) / (theta2 * theta);
      c2 = (theta2 / Scalar(2) + c - Scalar(1)) / (theta2 * theta2);
      c3 = (theta - s - theta2 * theta / Scalar(6)) / (theta2 * theta2 * theta);
    }
    const Mat3<Scalar> P = hatSO3(phi);
    const Mat3<Scalar> Rh = hatSO3(rho);
    const Mat3<Scalar> PR = P * Rh;
    const Mat3<Scalar> RP = Rh * P;
    const Mat3<Scalar> PRP = PR * P;
    return Scalar(0.5) * Rh + c1 * (PR + RP + PRP) + c2 * (P * PR + RP * P - Scalar(3) * PRP) +
           Scalar(0.5) * (c2 + Scalar(3) * c3) * (PRP * P + P * PRP);
  }

  SO3<Scalar> R_;
  Point t_;
};

// ----------------------------------------------------------------------------------------------- Sim3
// A similarity x -> s R x + t, with s > 0. Used to align trajectories and to merge maps of unknown scale.
template <typename Scalar_>
class Sim3 {
 public:
  using Scalar = Scalar_;
  using Tangent = Eigen::Matrix<Scalar, 7, 1>;
  using Adjoint = Eigen::Matrix<Scalar, 7, 7>;
  using Matrix4 = Eigen::Matrix<Scalar, 4, 4>;
  using Point = Vec3<Scalar>;
  static constexpr int kDoF = 7;

  Sim3() : t_(Point::Zero()), scale_(Scalar(1)) {}
  Sim3(Scalar scale, const SO3<Scalar>& R, const Point& t) : R_(R), t_(t), scale_(scale) {}
  explicit Sim3(const SE3<Scalar>& T) : R_(T.so3()), t_(T.translation()), scale_(Scalar(1)) {}

  static Sim3 identity() { return Sim3(); }

  // exp([rho; phi; sigma]) = (e^sigma, exp(phi), W(phi, sigma) rho),
  // W = integral_0^1 e^(sigma u) exp(u phi) du = A I + B [phi]x + C [phi]x^2.
  static Sim3 exp(const Tangent& zeta) {
    using std::exp;
    const Point phi = zeta.template segment<3>(3);
    const Scalar sigma = zeta(6);
    return Sim3(exp(sigma), SO3<Scalar>::exp(phi), W(phi, sigma) * zeta.template head<3>());
  }

  [[nodiscard]] Tangent log() const {
    using std::log;
    const Point phi = R_.log();
    const Scalar sigma = log(scale_);
    Tangent zeta;
    zeta.template head<3>() = W(phi, sigma).partialPivLu().solve(t_);
    zeta.template segment<3>(3) = phi;
    zeta(6) = sigma;
    return zeta;
  }

  [[nodiscard]] Sim3 inverse() const {
    const SO3<Scalar> R_inv = R_.inverse();
    const Scalar s_inv = Scalar(1) / scale_;
    return Sim3(s_inv, R_inv, -(s_inv * (R_inv * t_)));
  }

  Sim3 operator*(const Sim3& o) const { return Sim3(scale_ * o.scale_, R_ * o.R_, scale_ * (R_ * o.t_) + t_); }
  Sim3& operator*=(const Sim3& o) { return *this = *this * o; }
  Point operator*(const Point& p) const { return scale_ * (R_ * p) + t_; }

  [[nodiscard]] Scalar scale() const { return scale_; }
  [[nodiscard]] const SO3<Scalar>& so3() const { return R_; }
  [[nodiscard]] const Point& translation() const { return t_; }
  [[nodiscard]] Mat3<Scalar> rotationMatrix() const { return R_.matrix(); }

  [[nodiscard]] Matrix4 matrix() const {
    Matrix4 T = Matrix4::Identity();
    T.template topLeftCorner<3, 3>() = scale_ * R_.matrix();
    T.template topRightCorner<3, 1>() = t_;
    return T;
  }

  // Ad(S) = [sR, [t]x R, -t; 0, R, 0; 0, 0, 1].
  [[nodiscard]] Adjoint adjoint() const {
    const Mat3<Scalar> R = R_.matrix();
    Adjoint Ad = Adjoint::Zero();
    Ad.template block<3, 3>(0, 0) = scale_ * R;
    Ad.template block<3, 3>(0, 3) = hatSO3(t_) * R;
    Ad.template block<3, 1>(0, 6) = -t_;
    Ad.template block<3, 3>(3, 3) = R;
    Ad(6, 6) = Scalar(1);
    return Ad;
  }

  static Matrix4 hat(const Tangent& zeta) {
    Matrix4 m = Matrix4::Zero();
    m.template topLeftCorner<3, 3>() = hatSO3<Scalar>(zeta.template segment<3>(3)) + zeta(6) * Mat3<Scalar>::Identity();
    m.template topRightCorner<3, 1>() = zeta.template head<3>();
    return m;
  }
  static Tangent vee(const Matrix4& m) {
    Tangent zeta;
    zeta.template head<3>() = m.template topRightCorner<3, 1>();
    const Mat3<Scalar> A = m.template topLeftCorner<3, 3>();
    zeta.template segment<3>(3) = veeSO3<Scalar>(Scalar(0.5) * (A - A.transpose()));
    zeta(6) = A.trace() / Scalar(3);
    return zeta;
  }

  // ad(zeta) = [[phi]x + sigma I, [rho]x, -rho; 0, [phi]x, 0; 0, 0, 0].
  static Adjoint ad(const Tangent& zeta) {
    const Point rho = zeta.template head<3>();
    const Point phi = zeta.template segment<3>(3);
    Adjoint a = Adjoint::Zero();
    a.template block<3, 3>(0, 0) = hatSO3(phi) + zeta(6) * Mat3<Scalar>::Identity();
    a.template block<3, 3>(0, 3) = hatSO3(rho);
    a.template block<3, 1>(0, 6) = -rho;
    a.template block<3, 3>(3, 3) = hatSO3(phi);
    return a;
  }

  // Jl(zeta) = sum_k ad^k / (k+1)!,  Jr(zeta) = sum_k (-ad)^k / (k+1)!  (entire series, summed until the
  // terms stop contributing).
  static Adjoint leftJacobian(const Tangent& zeta) { return jacobianSeries(ad(zeta)); }
  static Adjoint rightJacobian(const Tangent& zeta) { return jacobianSeries(-ad(zeta)); }
  static Adjoint leftJacobianInverse(const Tangent& zeta) { return leftJacobian(zeta).partialPivLu().inverse(); }
  static Adjoint rightJacobianInverse(const Tangent& zeta) { return rightJacobian(zeta).partialPivLu().inverse(); }

  template <typename NewScalar>
  Sim3<NewScalar> cast() const {
    return Sim3<NewScalar>(NewScalar(scale_), R_.template cast<NewScalar>(), t_.template cast<NewScalar>());
  }

  // W(phi, sigma) of exp() above; public for tests.
  static Mat3<Scalar> W(const Point& phi, const Scalar& sigma) {
    using std::abs;
    using std::cos;
    using std::exp;
    using std::expm1;
    using std::sin;
    const Scalar theta = phi.norm();
    const Scalar theta2 = theta * theta;
    Scalar A;
    Scalar B;
    Scalar C;
    if (theta < Scalar(0.5)) {
      // B = int e^(su) sin(ut)/t du and C = int e^(su) (1 - cos(ut))/t^2 du expanded in t^2, with the
      // moments M_n = int_0^1 u^n e^(s u) du:
      //   B = sum_k (-1)^k t^2k / (2k+1)! M_(2k+1),  C = sum_k (-1)^k t^2k / (2k+2)! M_(2k+2).
      // The general form below cancels like eps/t^2 for small t. Seven terms: t^14/15! < 1e-16 at t = 0.5.
      Scalar M[kMoments];
      moments(sigma, M);
      A = M[0];
      B = Scalar(0);
      C = Scalar(0);
      Scalar power(1);       // (-1)^k t^2k
      double factorial = 1;  // (2k+1)!
      for (int k = 0; k < 7; ++k) {
        B += power / Scalar(factorial) * M[2 * k + 1];
        factorial *= (2 * k + 2);
        C += power / Scalar(factorial) * M[2 * k + 2];
        factorial *= (2 * k + 3);
        power = -power * theta2;
      }
    } else {
      A = abs(sigma) < Scalar(1e-12) ? Scalar(1) + sigma / Scalar(2) : Scalar(expm1(sigma)) / sigma;
      const Scalar es = exp(sigma);
      const Scalar st = sin(theta);
      const Scalar ct = cos(theta);
      const Scalar den = sigma * sigma + theta2;
      const Scalar I_sin = (es * (sigma * st - theta * ct) + theta) / den;  // int e^(su) sin(ut) du
      const Scalar I_cos = (es * (sigma * ct + theta * st) - sigma) / den;  // int e^(su) cos(ut) du
      B = I_sin / theta;
      C = (A - I_cos) / theta2;
    }
    const Mat3<Scalar> P = hatSO3(phi);
    return A * Mat3<Scalar>::Identity() + B * P + C * P * P;
  }

 private:
  static constexpr int kMoments = 15;

  // M_n(s) = int_0^1 u^n e^(s u) du for n = 0..14. For |s| <= 5 the power series sum_k s^k / (k! (n+k+1))
  // (its alternating terms for s < 0 cost at most e^5 eps ~ 3e-14); beyond, the upward recurrence
  // M_n = (e^s - n M_(n-1)) / s, whose error grows by at most prod n/|s| <= 14!/5^14 ~ 14.
  static void moments(const Scalar& s, Scalar (&M)[kMoments]) {
    using std::abs;
    using std::exp;
    using std::expm1;
    if (abs(s) <= Scalar(5)) {
      for (int n = 0; n < kMoments; ++n) {
        Scalar term(1);  // s^k / k!
        Scalar sum = Scalar(1) / Scalar(n + 1);
        for (int k = 1; k < 60; ++k) {
          term = term * s / Scalar(k);
          sum += term / Scalar(n + k + 1);
        }
        M[n] = sum;
      }
    } else {
      const Scalar es = exp(s);
      M[0] = Scalar(expm1(s)) / s;
      for (int n = 1; n < kMoments; ++n) M[n] = (es - Scalar(n) * M[n - 1]) / s;
    }
  }

  static Adjoint jacobianSeries(const Adjoint& x) {
    using std::abs;
    Adjoint sum = Adjoint::Identity();
    Adjoint power = Adjoint::Identity();  // x^k / (k+1)!
    for (int k = 1; k < 200; ++k) {
      power = power * x / Scalar(k + 1);
      sum += power;
      if (power.cwiseAbs().maxCoeff() < Scalar(1e-18) * (Scalar(1) + sum.cwiseAbs().maxCoeff())) break;
    }
    return sum;
  }

  SO3<Scalar> R_;
  Point t_;
  Scalar scale_;
};

using SO3d = SO3<double>;
using SE3d = SE3<double>;
using Sim3d = Sim3<double>;

}  // namespace cvislam::geometry
