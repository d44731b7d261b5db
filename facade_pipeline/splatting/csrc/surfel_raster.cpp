// Exact tile rasterizer of 2D Gaussian surfels on CPU (forward and analytic backward), OpenMP over tiles.
// Same semantics as facade_pipeline/splatting/blend_torch.py, which is the reference it is tested against.
// Plain C ABI (called through ctypes with pointers to contiguous torch tensors); float and double variants.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <algorithm>
#include <vector>
#include <omp.h>

namespace {

constexpr int TILE = 16;

template <typename S>
struct Consts {
  static constexpr S alpha_min = S(1.0 / 255.0);
  static constexpr S alpha_max = S(0.99);
  static constexpr S t_min = S(1e-4);
};

// One ray-splat evaluation: alpha and depth z at pixel (px, py), or false where the pair is skipped.
template <typename S>
struct Hit {
  S alpha, z, G, u, v, c2, cx, cy;
  S hx[3], hy[3];
  bool d3, clamped;
};

template <typename S>
// lowpass: the factor k of the low-pass term rho_2d = k |x - c|^2 (1 / sigma^2; 2 in 2DGS).
inline bool evaluate(const S* T, S opac, S rho_cut, S px, S py, S near_z, S lowpass, Hit<S>& h) {
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
    rho2 = lowpass * (dx * dx + dy * dy);
  }
  h.d3 = (c2 != 0) && (rho3 <= rho2);
  if (!h.d3 && !front) return false;
  const S rho = h.d3 ? rho3 : rho2;
  if (!(rho <= rho_cut)) return false;  // alpha < 1/255 for sure (rho_cut has a margin): skip the exp
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
inline void evaluate_backward(const S* T, S opac, S px, S py, S lowpass, const Hit<S>& h, S g_alpha, S g_z,
                              S* dT, S* d_opac) {
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
    const S dcx = -2 * lowpass * (px - h.cx) * g_rho;
    const S dcy = -2 * lowpass * (py - h.cy) * g_rho;
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
  S lowpass;  // low-pass factor k of rho_2d = k |x - c|^2
  std::vector<S> rho_cut;  // [N] rho beyond which alpha < 1/255 (with a margin)

  void prepare(int64_t N) {
    rho_cut.resize(size_t(N));
    for (int64_t i = 0; i < N; ++i) {
      const double o = double(opac[i]);
      rho_cut[size_t(i)] = o > 0 ? S(2 * std::log(std::max(o * 255.0, 1.0)) * 1.001 + 1e-3) : S(-1);
    }
  }
};

inline bool outside_x(const double* bd, double px) { return px < bd[0] || px > bd[2]; }

// Positions (in the tile's list, front to back) of the splats whose support meets pixel row py of the tile
// spanning pixel centres [px0, px1]: each pixel of the row then only tests these.
inline void row_candidates(const double* bounds, const int64_t* ids, int64_t begin, int64_t end, double py,
                           double px0, double px1, std::vector<int32_t>& out) {
  out.clear();
  for (int64_t k = begin; k < end; ++k) {
    const double* bd = bounds + 4 * ids[k];
    if (bd[1] <= py && py <= bd[3] && bd[0] <= px1 && px0 <= bd[2]) out.push_back(int32_t(k - begin));
  }
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
    std::vector<int32_t> row;
    for (int64_t j = 0; j < TILE; ++j) {
      const int64_t iy = ty * TILE + j;
      if (iy >= g.height) break;
      row_candidates(sp.bounds, ids, begin, end, double(S(g.y0 + iy) + S(0.5)),
                     double(S(g.x0 + tx * TILE) + S(0.5)), double(S(g.x0 + tx * TILE + TILE - 1) + S(0.5)), row);
      for (int64_t i = 0; i < TILE; ++i) {
        const int64_t ix = tx * TILE + i;
        if (ix >= g.width) break;
        const S px = S(g.x0 + ix) + S(0.5), py = S(g.y0 + iy) + S(0.5);
        std::fill(acc.begin(), acc.end(), S(0));
        S T = 1, M1 = 0, M2 = 0, dist = 0, depth = 0, median = 0, nrm[3] = {0, 0, 0};
        int32_t last = 0;
        int64_t median_id = -1;
        for (const int32_t pos : row) {
          const int64_t k = begin + pos;
          const int64_t id = ids[k];
          if (outside_x(sp.bounds + 4 * id, double(px))) continue;
          Hit<S> h;
          if (!evaluate(sp.T + 9 * id, sp.opac[id], sp.rho_cut[size_t(id)], px, py, near_z, sp.lowpass, h)) continue;
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
    // tiles dealt round robin, not on demand: each thread's buffer then sums the same tiles in the same
    // order at every call, so the gradients are reproducible bit for bit at a given thread count
    const int team = omp_get_num_threads();
    for (int64_t t = tid; t < n_tiles; t += team) {
      const int64_t tx = t % g.tiles_x, ty = t / g.tiles_x;
      const int64_t begin = offsets[t], end = offsets[t + 1];
      std::vector<int32_t> row;
      for (int64_t j = 0; j < TILE; ++j) {
        const int64_t iy = ty * TILE + j;
        if (iy >= g.height) break;
        row_candidates(sp.bounds, ids, begin, end, double(S(g.y0 + iy) + S(0.5)),
                       double(S(g.x0 + tx * TILE) + S(0.5)), double(S(g.x0 + tx * TILE + TILE - 1) + S(0.5)),
                       row);
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
          for (auto it = row.rbegin(); it != row.rend(); ++it) {
            if (*it >= out_last[p]) continue;
            const int64_t id = ids[begin + *it];
            if (outside_x(sp.bounds + 4 * id, double(px))) continue;
            Hit<S> h;
            const S* Ti = sp.T + 9 * id;
            if (!evaluate(Ti, sp.opac[id], sp.rho_cut[size_t(id)], px, py, near_z, sp.lowpass, h)) continue;
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
            evaluate_backward(Ti, sp.opac[id], px, py, sp.lowpass, h, g_alpha, g_z, b, b + 9);
            for (int64_t c = 0; c < F; ++c) b[10 + c] += w * gf[c];
            for (int c = 0; c < 3; ++c) b[10 + F + c] += w * gn[c];
          }
        }
      }
    }
#pragma omp barrier
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


// ---- binning: conservative pixel support and tile lists (mirrors facade_pipeline/splatting/binning.py) ----

constexpr double RHO_MARGIN = 1e-3;
constexpr double PIXEL_MARGIN = 0.25;

// Bounds of n / d over [n0, n1] x [d0, d1] with d > 0 (attained at the corners).
inline void ratio_bounds(double n0, double n1, double d0, double d1, double& lo, double& hi) {
  const double c[4] = {n0 / d0, n0 / d1, n1 / d0, n1 / d1};
  lo = std::min(std::min(c[0], c[1]), std::min(c[2], c[3]));
  hi = std::max(std::max(c[0], c[1]), std::max(c[2], c[3]));
}

// Pixel box (x_min, y_min, x_max, y_max) of one splat's support; false when it has none.
template <typename S>
bool support_bounds(const S* Tf, S opac_s, double near_z, double lowpass, double* box) {
  double T[9];
  for (int k = 0; k < 9; ++k) {
    T[k] = double(Tf[k]);
    if (!std::isfinite(T[k])) return false;
  }
  const double o = double(opac_s);
  if (!(o >= (1.0 / 255.0) * (1 - 1e-6))) return false;
  double R2 = 2 * std::log(std::max(o * 255.0, 1.0));
  R2 = R2 * (1 + RHO_MARGIN) + RHO_MARGIN;
  const double R = std::sqrt(R2);
  const double* e = T + 6;
  const double e_xy = std::sqrt(e[0] * e[0] + e[1] * e[1]);
  const double z_lo = e[2] - R * e_xy, z_hi = e[2] + R * e_xy;
  double lo3[2] = {INFINITY, INFINITY}, hi3[2] = {-INFINITY, -INFINITY};
  const bool disk_ok = z_hi >= near_z;
  if (disk_ok) {
    for (int r = 0; r < 2; ++r) {
      const double* row = T + 3 * r;
      if (z_lo >= near_z) {  // the whole disk is beyond the near plane: exact extent of the ellipse
        const double A = e[2] * e[2] - R2 * e_xy * e_xy;
        const double B = row[2] * e[2] - R2 * (row[0] * e[0] + row[1] * e[1]);
        const double C = row[2] * row[2] - R2 * (row[0] * row[0] + row[1] * row[1]);
        const double mid = B / A;
        const double half = std::sqrt(std::max(mid * mid - C / A, 0.0));
        lo3[r] = mid - half;
        hi3[r] = mid + half;
      } else {
        const double n_half = R * std::sqrt(row[0] * row[0] + row[1] * row[1]);
        ratio_bounds(row[2] - n_half, row[2] + n_half, std::max(z_lo, near_z), std::max(z_hi, near_z), lo3[r],
                     hi3[r]);
      }
    }
  }
  const bool centre_ok = e[2] >= near_z;
  double lo2[2] = {INFINITY, INFINITY}, hi2[2] = {-INFINITY, -INFINITY};
  if (centre_ok) {
    const double rad = std::sqrt(R2 / lowpass);
    const double c[2] = {T[2] / e[2], T[5] / e[2]};
    for (int r = 0; r < 2; ++r) {
      lo2[r] = c[r] - rad;
      hi2[r] = c[r] + rad;
    }
  }
  if (!disk_ok && !centre_ok) return false;
  for (int r = 0; r < 2; ++r) {
    double lo = std::min(lo3[r], lo2[r]) - PIXEL_MARGIN, hi = std::max(hi3[r], hi2[r]) + PIXEL_MARGIN;
    if (std::isnan(lo)) lo = -INFINITY;
    if (std::isnan(hi)) hi = INFINITY;
    box[r] = lo;
    box[2 + r] = hi;
  }
  return true;
}

// Inclusive tile range [t0, t1] of pixel coordinates [lo, hi] clipped to the window; false when empty.
inline bool tile_range(double lo, double hi, int64_t origin, int64_t size, int64_t n_tiles, int64_t& t0,
                       int64_t& t1) {
  lo = std::max(lo, double(origin));
  hi = std::min(hi, double(origin + size));
  if (!(lo <= hi)) return false;
  t0 = std::max<int64_t>(0, int64_t(std::floor((lo - origin) / TILE)));
  t1 = std::min<int64_t>(n_tiles - 1, int64_t(std::floor((hi - origin) / TILE)));
  return t0 <= t1;
}

template <typename S>
void bin_count(const S* T, const S* opac, int64_t N, double near_z, double lowpass, Geometry g, int threads,
               double* bounds, int64_t* rect, int64_t* tile_counts) {
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i = 0; i < N; ++i) {
    double* box = bounds + 4 * i;
    int64_t* rc = rect + 4 * i;
    rc[0] = 0, rc[1] = -1, rc[2] = 0, rc[3] = -1;
    if (!support_bounds(T + 9 * i, opac[i], near_z, lowpass, box)) {
      box[0] = box[1] = INFINITY;
      box[2] = box[3] = -INFINITY;
      continue;
    }
    int64_t tx0, tx1, ty0, ty1;
    if (tile_range(box[0], box[2], g.x0, g.width, g.tiles_x, tx0, tx1) &&
        tile_range(box[1], box[3], g.y0, g.height, g.tiles_y, ty0, ty1)) {
      rc[0] = tx0, rc[1] = tx1, rc[2] = ty0, rc[3] = ty1;
    }
  }
  for (int64_t i = 0; i < N; ++i) {
    const int64_t* rc = rect + 4 * i;
    for (int64_t ty = rc[2]; ty <= rc[3]; ++ty)
      for (int64_t tx = rc[0]; tx <= rc[1]; ++tx) ++tile_counts[ty * g.tiles_x + tx];
  }
}

// Counting sort: visiting splats front to back keeps each tile's list in depth order.
void bin_fill(const int64_t* order, int64_t N, const int64_t* rect, int64_t tiles_x, int64_t* cursor,
              int64_t* ids) {
  for (int64_t j = 0; j < N; ++j) {
    const int64_t i = order[j];
    const int64_t* rc = rect + 4 * i;
    for (int64_t ty = rc[2]; ty <= rc[3]; ++ty)
      for (int64_t tx = rc[0]; tx <= rc[1]; ++tx) ids[cursor[ty * tiles_x + tx]++] = i;
  }
}

}  // namespace

#define SURFEL_EXPORT extern "C" __attribute__((visibility("default")))

#define DEFINE_ENTRY_POINTS(S, SUFFIX)                                                                       \
  SURFEL_EXPORT void surfel_forward_##SUFFIX(                                                                \
      const S* T, const S* opac, const S* feat, const S* normal, const double* bounds, int64_t F, int64_t N, \
      const int64_t* offsets, const int64_t* ids, int64_t x0, int64_t y0, int64_t width, int64_t height,     \
      int64_t tiles_x, int64_t tiles_y, double near_z, double far_z, double lowpass, int threads,            \
      S* out_feat, S* out_T, S* out_depth, S* out_normal, S* out_median, S* out_dist, S* out_M1, S* out_M2,  \
      int32_t* out_last, int64_t* out_median_id) {                                                           \
    Splats<S> sp{T, opac, feat, normal, bounds, F, S(lowpass), {}};                                          \
    sp.prepare(N);                                                                                           \
    forward<S>(sp, offsets, ids, Geometry{x0, y0, width, height, tiles_x, tiles_y}, S(near_z), S(far_z),    \
               threads, out_feat, out_T, out_depth, out_normal, out_median, out_dist, out_M1, out_M2,        \
               out_last, out_median_id);                                                                     \
  }                                                                                                          \
  SURFEL_EXPORT void surfel_backward_##SUFFIX(                                                               \
      const S* T, const S* opac, const S* feat, const S* normal, const double* bounds, int64_t F, int64_t N, \
      const int64_t* offsets, const int64_t* ids, int64_t x0, int64_t y0, int64_t width, int64_t height,     \
      int64_t tiles_x, int64_t tiles_y, double near_z, double far_z, double lowpass, int threads,            \
      const S* out_T, const S* out_M1, const S* out_M2, const int32_t* out_last, const int64_t* out_median_id, \
      const S* g_feat, const S* g_T, const S* g_depth, const S* g_normal, const S* g_median,                 \
      const S* g_dist, S* dT, S* d_opac, S* d_feat, S* d_normal) {                                           \
    Splats<S> sp{T, opac, feat, normal, bounds, F, S(lowpass), {}};                                          \
    sp.prepare(N);                                                                                           \
    backward<S>(sp, offsets, ids, Geometry{x0, y0, width, height, tiles_x, tiles_y}, S(near_z), S(far_z),   \
                threads, out_T, out_M1, out_M2, out_last, out_median_id, g_feat, g_T, g_depth, g_normal,      \
                g_median, g_dist, N, dT, d_opac, d_feat, d_normal);                                          \
  }

#define DEFINE_BIN_ENTRY_POINT(S, SUFFIX)                                                                     \
  SURFEL_EXPORT void surfel_bin_count_##SUFFIX(const S* T, const S* opac, int64_t N, double near_z,              \
                                               double lowpass, int64_t x0, int64_t y0, int64_t width,             \
                                               int64_t height, int64_t tiles_x, int64_t tiles_y, int threads,     \
                                               double* bounds, int64_t* rect, int64_t* tile_counts) {             \
    bin_count<S>(T, opac, N, near_z, lowpass, Geometry{x0, y0, width, height, tiles_x, tiles_y}, threads,       \
                 bounds, rect, tile_counts);                                                                      \
  }

SURFEL_EXPORT void surfel_bin_fill(const int64_t* order, int64_t N, const int64_t* rect, int64_t tiles_x,
                                   int64_t* cursor, int64_t* ids) {
  bin_fill(order, N, rect, tiles_x, cursor, ids);
}

DEFINE_BIN_ENTRY_POINT(float, f32)
DEFINE_BIN_ENTRY_POINT(double, f64)
DEFINE_ENTRY_POINTS(float, f32)
DEFINE_ENTRY_POINTS(double, f64)
