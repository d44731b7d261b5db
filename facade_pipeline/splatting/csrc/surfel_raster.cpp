// Exact tile rasterizer of 2D Gaussian surfels on CPU (forward and analytic backward), OpenMP over tiles.
// Same semantics as facade_pipeline/splatting/blend_torch.py, which is the reference it is tested against.
// Plain C ABI (called through ctypes with pointers to contiguous torch tensors); float and double variants.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>
#include <omp.h>

namespace {

constexpr int TILE = 16;

template <typename S>
struct Consts {
  static constexpr S alpha_min = S(1.0 / 255.0);
  static constexpr S alpha_max = S(0.99);
  static constexpr S t_min = S(1e-4);
  static constexpr S lowpass = S(2.0);
};

// One ray-splat evaluation: alpha and depth z at pixel (px, py), or false where the pair is skipped.
template <typename S>
struct Hit {
  S alpha, z, G, u, v, c2, cx, cy;
  S hx[3], hy[3];
  bool d3, clamped;
};

template <typename S>
inline bool evaluate(const S* T, S opac, S px, S py, S near_z, Hit<S>& h) {
  const S* a = T;
  const S* b = T + 3;
  const S* e = T + 6;
  for (int k = 0; k < 3; ++k) {
    h.hx[k] = a[k] - px * e[k];
    h.hy[k] = b[k] - py * e[k];
  }
  const S c0 = h.hx[1] * h.hy[2] - h.hx[2] * h.hy[1];
  const S c1 = h.hx[2] * h.hy[0] - h.hx[0] * h.hy[2];
  const S c2 = h.hx[0] * h.hy[1] - h.hx[1] * h.hy[0];
  const bool front = e[2] >= near_z;
  S rho3 = INFINITY, rho2 = INFINITY;
  if (c2 != 0) {
    h.u = c0 / c2;
    h.v = c1 / c2;
    rho3 = h.u * h.u + h.v * h.v;
  }
  if (front) {
    h.cx = a[2] / e[2];
    h.cy = b[2] / e[2];
    const S dx = px - h.cx, dy = py - h.cy;
    rho2 = Consts<S>::lowpass * (dx * dx + dy * dy);
  }
  h.d3 = (c2 != 0) && (rho3 <= rho2);
  if (!h.d3 && !front) return false;
  const S rho = h.d3 ? rho3 : rho2;
  if (!std::isfinite(rho)) return false;
  h.z = h.d3 ? e[0] * h.u + e[1] * h.v + e[2] : e[2];
  if (!(h.z >= near_z)) return false;
  h.c2 = c2;
  h.G = std::exp(S(-0.5) * rho);
  S alpha = opac * h.G;
  h.clamped = alpha > Consts<S>::alpha_max;
  if (h.clamped) alpha = Consts<S>::alpha_max;
  if (!(alpha >= Consts<S>::alpha_min)) return false;
  h.alpha = alpha;
  return true;
}

// Chain dL/dalpha and dL/dz of one evaluated pair into dL/dT (9) and dL/dopacity.
template <typename S>
inline void evaluate_backward(const S* T, S opac, S px, S py, const Hit<S>& h, S g_alpha, S g_z, S* dT,
                              S* d_opac) {
  const S* e = T + 6;
  S gG = 0;
  if (!h.clamped) {
    *d_opac += g_alpha * h.G;
    gG = g_alpha * opac;
  }
  const S g_rho = S(-0.5) * h.G * gG;
  if (h.d3) {
    const S du = 2 * h.u * g_rho + g_z * e[0];
    const S dv = 2 * h.v * g_rho + g_z * e[1];
    dT[6] += g_z * h.u;
    dT[7] += g_z * h.v;
    dT[8] += g_z;
    const S dc[3] = {du / h.c2, dv / h.c2, -(du * h.u + dv * h.v) / h.c2};
    // c = hx x hy: dL/dhx = hy x dc, dL/dhy = dc x hx
    const S dhx[3] = {h.hy[1] * dc[2] - h.hy[2] * dc[1], h.hy[2] * dc[0] - h.hy[0] * dc[2],
                      h.hy[0] * dc[1] - h.hy[1] * dc[0]};
    const S dhy[3] = {dc[1] * h.hx[2] - dc[2] * h.hx[1], dc[2] * h.hx[0] - dc[0] * h.hx[2],
                      dc[0] * h.hx[1] - dc[1] * h.hx[0]};
    for (int k = 0; k < 3; ++k) {
      dT[k] += dhx[k];
      dT[3 + k] += dhy[k];
      dT[6 + k] -= px * dhx[k] + py * dhy[k];
    }
  } else {
    const S dcx = -2 * Consts<S>::lowpass * (px - h.cx) * g_rho;
    const S dcy = -2 * Consts<S>::lowpass * (py - h.cy) * g_rho;
    dT[2] += dcx / e[2];
    dT[5] += dcy / e[2];
    dT[8] += g_z - (dcx * h.cx + dcy * h.cy) / e[2];
  }
}

struct Geometry {
  int64_t x0, y0, width, height, tiles_x, tiles_y;
};

template <typename S>
struct Splats {
  const S* T;        // [N, 9]
  const S* opac;     // [N]
  const S* feat;     // [N, F]
  const S* normal;   // [N, 3]
  const double* bounds;  // [N, 4] conservative pixel support
  int64_t F;
};

inline bool outside(const double* bd, double px, double py) {
  return px < bd[0] || px > bd[2] || py < bd[1] || py > bd[3];
}

template <typename S>
void forward(const Splats<S>& sp, const int64_t* offsets, const int64_t* ids, Geometry g, S near_z, S far_z,
             int threads, S* out_feat, S* out_T, S* out_depth, S* out_normal, S* out_median, S* out_dist,
             S* out_M1, S* out_M2, int32_t* out_last, int64_t* out_median_id) {
  const S mscale = far_z / (far_z - near_z);
  const int64_t n_tiles = g.tiles_x * g.tiles_y;
  const int64_t F = sp.F;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t t = 0; t < n_tiles; ++t) {
    const int64_t tx = t % g.tiles_x, ty = t / g.tiles_x;
    const int64_t begin = offsets[t], end = offsets[t + 1];
    std::vector<S> acc(F);
    for (int64_t j = 0; j < TILE; ++j) {
      const int64_t iy = ty * TILE + j;
      if (iy >= g.height) break;
      for (int64_t i = 0; i < TILE; ++i) {
        const int64_t ix = tx * TILE + i;
        if (ix >= g.width) break;
        const S px = S(g.x0 + ix) + S(0.5), py = S(g.y0 + iy) + S(0.5);
        std::fill(acc.begin(), acc.end(), S(0));
        S T = 1, M1 = 0, M2 = 0, dist = 0, depth = 0, median = 0, nrm[3] = {0, 0, 0};
        int32_t last = 0;
        int64_t median_id = -1;
        for (int64_t k = begin; k < end; ++k) {
          const int64_t id = ids[k];
          if (outside(sp.bounds + 4 * id, double(px), double(py))) continue;
          Hit<S> h;
          if (!evaluate(sp.T + 9 * id, sp.opac[id], px, py, near_z, h)) continue;
          const S T_next = T * (1 - h.alpha);
          if (T_next < Consts<S>::t_min) break;
          const S w = h.alpha * T;
          const S m = mscale * (1 - near_z / h.z);
          dist += w * (m * m * (1 - T) + M2 - 2 * m * M1);
          if (T > S(0.5)) {
            median = h.z;
            median_id = id;
          }
          M1 += w * m;
          M2 += w * m * m;
          depth += w * h.z;
          const S* f = sp.feat + F * id;
          for (int64_t c = 0; c < F; ++c) acc[c] += w * f[c];
          for (int c = 0; c < 3; ++c) nrm[c] += w * sp.normal[3 * id + c];
          T = T_next;
          last = int32_t(k - begin + 1);
        }
        const int64_t p = iy * g.width + ix;
        for (int64_t c = 0; c < F; ++c) out_feat[p * F + c] = acc[c];
        for (int c = 0; c < 3; ++c) out_normal[p * 3 + c] = nrm[c];
        out_T[p] = T;
        out_depth[p] = depth;
        out_median[p] = median;
        out_dist[p] = dist;
        out_M1[p] = M1;
        out_M2[p] = M2;
        out_last[p] = last;
        out_median_id[p] = median_id;
      }
    }
  }
}

// Backward of one pixel, back to front. With v_i = (f_i, z_i, n_i, 1, m_i, m_i^2) and the pixel's upstream
// gradient g on (features, depth sum, normal, alpha, M1, M2) -- the distortion being A M2 - M1^2 with
// A = sum w -- dL/dalpha_i = T_i (g.v_i) - (sum_{j>i} w_j g.v_j) / (1 - alpha_i).
template <typename S>
void backward(const Splats<S>& sp, const int64_t* offsets, const int64_t* ids, Geometry g, S near_z, S far_z,
              int threads, const S* out_T, const S* out_M1, const S* out_M2, const int32_t* out_last,
              const int64_t* out_median_id, const S* g_feat, const S* g_T, const S* g_depth, const S* g_normal,
              const S* g_median, const S* g_dist, int64_t N, S* dT, S* d_opac, S* d_feat, S* d_normal) {
  const S mscale = far_z / (far_z - near_z);
  const int64_t n_tiles = g.tiles_x * g.tiles_y;
  const int64_t F = sp.F;
  const int64_t stride = 9 + 1 + F + 3;
  std::vector<std::vector<S>> buffers(threads);
#pragma omp parallel num_threads(threads)
  {
    const int tid = omp_get_thread_num();
    std::vector<S>& buf = buffers[tid];
    buf.assign(size_t(N * stride), S(0));
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int64_t tx = t % g.tiles_x, ty = t / g.tiles_x;
      const int64_t begin = offsets[t];
      for (int64_t j = 0; j < TILE; ++j) {
        const int64_t iy = ty * TILE + j;
        if (iy >= g.height) break;
        for (int64_t i = 0; i < TILE; ++i) {
          const int64_t ix = tx * TILE + i;
          if (ix >= g.width) break;
          const int64_t p = iy * g.width + ix;
          const S px = S(g.x0 + ix) + S(0.5), py = S(g.y0 + iy) + S(0.5);
          const S T_final = out_T[p];
          const S A = 1 - T_final;
          const S* gf = g_feat + p * F;
          const S* gn = g_normal + 3 * p;
          const S gD = g_depth[p];
          const S gA = -g_T[p] + g_dist[p] * out_M2[p];
          const S gM1 = -2 * g_dist[p] * out_M1[p];
          const S gM2 = g_dist[p] * A;
          S T = T_final, suffix = 0;
          for (int64_t k = begin + out_last[p] - 1; k >= begin; --k) {
            const int64_t id = ids[k];
            if (outside(sp.bounds + 4 * id, double(px), double(py))) continue;
            Hit<S> h;
            const S* Ti = sp.T + 9 * id;
            if (!evaluate(Ti, sp.opac[id], px, py, near_z, h)) continue;
            const S one_minus = 1 - h.alpha;
            T = T / one_minus;  // transmittance before this splat
            const S w = h.alpha * T;
            const S m = mscale * (1 - near_z / h.z);
            const S* f = sp.feat + F * id;
            const S* n = sp.normal + 3 * id;
            S gv = gD * h.z + gA + gM1 * m + gM2 * m * m;
            for (int64_t c = 0; c < F; ++c) gv += gf[c] * f[c];
            for (int c = 0; c < 3; ++c) gv += gn[c] * n[c];
            const S g_alpha = T * gv - suffix / one_minus;
            suffix += w * gv;
            const S dm_dz = mscale * near_z / (h.z * h.z);
            S g_z = w * (gD + (gM1 + 2 * gM2 * m) * dm_dz);
            if (id == out_median_id[p]) g_z += g_median[p];
            S* b = buf.data() + id * stride;
            evaluate_backward(Ti, sp.opac[id], px, py, h, g_alpha, g_z, b, b + 9);
            for (int64_t c = 0; c < F; ++c) b[10 + c] += w * gf[c];
            for (int c = 0; c < 3; ++c) b[10 + F + c] += w * gn[c];
          }
        }
      }
    }
#pragma omp for schedule(static)
    for (int64_t id = 0; id < N; ++id) {
      for (int th = 0; th < threads; ++th) {
        if (buffers[th].empty()) continue;  // the team may have fewer threads than asked for
        const S* b = buffers[th].data() + id * stride;
        for (int k = 0; k < 9; ++k) dT[9 * id + k] += b[k];
        d_opac[id] += b[9];
        for (int64_t c = 0; c < F; ++c) d_feat[F * id + c] += b[10 + c];
        for (int c = 0; c < 3; ++c) d_normal[3 * id + c] += b[10 + F + c];
      }
    }
  }
}

}  // namespace

#define SURFEL_EXPORT extern "C" __attribute__((visibility("default")))

#define DEFINE_ENTRY_POINTS(S, SUFFIX)                                                                       \
  SURFEL_EXPORT void surfel_forward_##SUFFIX(                                                                \
      const S* T, const S* opac, const S* feat, const S* normal, const double* bounds, int64_t F,            \
      const int64_t* offsets, const int64_t* ids, int64_t x0, int64_t y0, int64_t width, int64_t height,     \
      int64_t tiles_x, int64_t tiles_y, double near_z, double far_z, int threads, S* out_feat, S* out_T,     \
      S* out_depth, S* out_normal, S* out_median, S* out_dist, S* out_M1, S* out_M2, int32_t* out_last,       \
      int64_t* out_median_id) {                                                                              \
    Splats<S> sp{T, opac, feat, normal, bounds, F};                                                          \
    forward<S>(sp, offsets, ids, Geometry{x0, y0, width, height, tiles_x, tiles_y}, S(near_z), S(far_z),    \
               threads, out_feat, out_T, out_depth, out_normal, out_median, out_dist, out_M1, out_M2,        \
               out_last, out_median_id);                                                                     \
  }                                                                                                          \
  SURFEL_EXPORT void surfel_backward_##SUFFIX(                                                               \
      const S* T, const S* opac, const S* feat, const S* normal, const double* bounds, int64_t F, int64_t N, \
      const int64_t* offsets, const int64_t* ids, int64_t x0, int64_t y0, int64_t width, int64_t height,     \
      int64_t tiles_x, int64_t tiles_y, double near_z, double far_z, int threads, const S* out_T,            \
      const S* out_M1, const S* out_M2, const int32_t* out_last, const int64_t* out_median_id,               \
      const S* g_feat, const S* g_T, const S* g_depth, const S* g_normal, const S* g_median,                 \
      const S* g_dist, S* dT, S* d_opac, S* d_feat, S* d_normal) {                                           \
    Splats<S> sp{T, opac, feat, normal, bounds, F};                                                          \
    backward<S>(sp, offsets, ids, Geometry{x0, y0, width, height, tiles_x, tiles_y}, S(near_z), S(far_z),   \
                threads, out_T, out_M1, out_M2, out_last, out_median_id, g_feat, g_T, g_depth, g_normal,      \
                g_median, g_dist, N, dT, d_opac, d_feat, d_normal);                                          \
  }

DEFINE_ENTRY_POINTS(float, f32)
DEFINE_ENTRY_POINTS(double, f64)
