// Shading of hit streams (see shade.h): scalar reference. Each ray is shaded from its own data
// and hit only, so the image does not depend on how rays are grouped into streams or tasks.
#include "kernels/shade.h"

#include <algorithm>
#include <limits>

namespace rs {

void ShadeStats::Merge(const ShadeStats& o) {
  rays += o.rays;
  shading_calls += o.shading_calls;
  misses += o.misses;
  light_tests += o.light_tests;
  texture_fetches += o.texture_fetches;
  culled += o.culled;
  for (int k = 0; k < kNumRayKinds; ++k) spawned[k] += o.spawned[k];
}

glm::vec3 SampleTexture(const Texture& texture, glm::vec2 uv) {
  const int w = texture.width;
  const int h = texture.height;
  if (w <= 0 || h <= 0 || texture.rgb.size() < static_cast<size_t>(w) * h * 3) {
    return glm::vec3(1.0f);
  }
  float u = std::isfinite(uv.x) ? uv.x - std::floor(uv.x) : 0.0f;  // wrap to [0, 1]
  float v = std::isfinite(uv.y) ? uv.y - std::floor(uv.y) : 0.0f;
  // Texel centres at (i + 0.5) / w; v = 0 is the bottom row (h - 1).
  const float x = u * static_cast<float>(w) - 0.5f;
  const float y = (1.0f - v) * static_cast<float>(h) - 0.5f;
  const float fx0 = std::floor(x);
  const float fy0 = std::floor(y);
  const float fx = x - fx0;
  const float fy = y - fy0;
  auto wrap = [](int i, int n) { return ((i % n) + n) % n; };
  const int x0 = wrap(static_cast<int>(fx0), w);
  const int x1 = wrap(static_cast<int>(fx0) + 1, w);
  const int y0 = wrap(static_cast<int>(fy0), h);
  const int y1 = wrap(static_cast<int>(fy0) + 1, h);
  auto texel = [&](int tx, int ty) {
    const float* p = texture.rgb.data() + (static_cast<size_t>(ty) * w + tx) * 3;
    return glm::vec3(p[0], p[1], p[2]);
  };
  const glm::vec3 top = texel(x0, y0) * (1.0f - fx) + texel(x1, y0) * fx;
  const glm::vec3 bottom = texel(x0, y1) * (1.0f - fx) + texel(x1, y1) * fx;
  return top * (1.0f - fy) + bottom * fy;
}

namespace {

float MaxChannel(const glm::vec3& c) { return std::max(c.x, std::max(c.y, c.z)); }

void PushRay(RayStream& out, const glm::vec3& o, const glm::vec3& d, float tmax,
             uint32_t pixel, const glm::vec3& w, int32_t depth, RayKind kind) {
  out.Push(o.x, o.y, o.z, d.x, d.y, d.z, 0.0f, tmax, pixel, w.x, w.y, w.z, depth, kind);
}

}  // namespace

namespace ref {

void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, Framebuffer& fb, RayStream& secondary,
           ShadeStats* stats) {
  HWY_DASSERT(hits.size == rays.size);
  const SceneFeatures& features = scene.features;
  const bool any_bounce = features.reflection || features.transmission;
  const bool textured = features.textures && !scene.uvs.empty();
  const bool smooth = !scene.normals.empty();
  const bool background = MaxChannel(scene.background) > 0.0f;
  const float inf = std::numeric_limits<float>::infinity();
  ShadeStats s;
  s.rays = rays.size;

  for (size_t i = 0; i < rays.size; ++i) {
    HWY_DASSERT(rays.kind[i] != static_cast<int32_t>(RayKind::kShadow));
    const glm::vec3 w(rays.wr[i], rays.wg[i], rays.wb[i]);
    const uint32_t pixel = rays.pixel[i];
    const int32_t prim = hits.prim[i];
    if (prim < 0) {
      ++s.misses;
      if (background) {
        const glm::vec3 c = w * scene.background;
        fb.Add(pixel, c.x, c.y, c.z);
      }
      continue;
    }
    HWY_DASSERT(static_cast<size_t>(prim) < scene.triangles.size());
    ++s.shading_calls;
    const int32_t depth = rays.depth[i];
    const glm::uvec3 tri = scene.triangles[prim];
    const glm::vec3& p0 = scene.positions[tri.x];
    const glm::vec3& p1 = scene.positions[tri.y];
    const glm::vec3& p2 = scene.positions[tri.z];
    const float u = hits.u[i];
    const float v = hits.v[i];
    const float b0 = 1.0f - u - v;
    // p from barycentrics: its error is relative to the vertices, which OffsetRayOrigin's
    // ulp-scaled step covers (t along the ray would add the error of a long ray).
    const glm::vec3 p = b0 * p0 + u * p1 + v * p2;
    const glm::vec3 d = glm::normalize(glm::vec3(rays.dx[i], rays.dy[i], rays.dz[i]));

    // Geometric normal: the face normal by winding (outward for consistently wound closed
    // meshes), flipped to face the incoming ray. Zero-area triangles are never hit (Accel).
    const glm::vec3 n_face = glm::normalize(glm::cross(p1 - p0, p2 - p0));
    const bool entering = glm::dot(d, n_face) < 0.0f;
    const glm::vec3 ng = entering ? n_face : -n_face;
    glm::vec3 ns = ng;
    if (smooth) {
      const glm::vec3 n = b0 * scene.normals[tri.x] + u * scene.normals[tri.y] +
                          v * scene.normals[tri.z];
      const float len2 = glm::dot(n, n);
      if (len2 > 1e-20f && std::isfinite(len2)) {
        ns = n / std::sqrt(len2);
        if (glm::dot(ns, ng) < 0.0f) ns = -ns;  // same hemisphere as ng
      }
    }

    const Material& mat = scene.materials[scene.material_ids[prim]];
    glm::vec3 kd = mat.diffuse;
    if (textured && mat.texture >= 0 &&
        static_cast<size_t>(mat.texture) < scene.textures.size()) {
      const glm::vec2 uv = b0 * scene.uvs[tri.x] + u * scene.uvs[tri.y] + v * scene.uvs[tri.z];
      kd *= SampleTexture(scene.textures[mat.texture], uv);
      ++s.texture_fetches;
    }

    // The origin on the incoming side, shared by shadow and reflection rays.
    const glm::vec3 front = OffsetRayOrigin(p, ng);
    const float local = std::clamp(1.0f - mat.reflectivity - mat.transmission, 0.0f, 1.0f);
    if (local > 0.0f) {
      const glm::vec3 wl = w * local;
      const glm::vec3 ambient = wl * scene.ambient * kd;
      if (MaxChannel(ambient) > 0.0f) fb.Add(pixel, ambient.x, ambient.y, ambient.z);

      if (features.lights) {
        const bool highlight = features.specular && mat.shininess > 0.0f &&
                               MaxChannel(mat.specular) > 0.0f;
        const glm::vec3 view = -d;
        for (const PointLight& light : scene.lights) {
          ++s.light_tests;
          const glm::vec3 to_light = light.position - p;
          const float dist2 = glm::dot(to_light, to_light);
          if (!(dist2 > 0.0f)) continue;
          const glm::vec3 l = to_light / std::sqrt(dist2);
          // Above the surface: on the incoming side of the geometry (else the shadow ray
          // would cross the surface) and of the shading normal.
          const float cos_ns = glm::dot(ns, l);
          if (glm::dot(ng, l) <= 0.0f || cos_ns <= 0.0f) continue;
          glm::vec3 c = kd * cos_ns;
          if (highlight) {
            const float rv = std::max(0.0f, glm::dot(Reflect(-l, ns), view));
            c += mat.specular * std::pow(rv, mat.shininess);
          }
          const float atten = light.falloff > 0.0f ? 1.0f / (1.0f + light.falloff * dist2) : 1.0f;
          const glm::vec3 contrib = c * light.color * atten * wl;
          if (!(MaxChannel(contrib) > 0.0f)) continue;
          PushRay(secondary, front, light.position - front, kShadowTmax, pixel, contrib, depth,
                  RayKind::kShadow);
          ++s.spawned[static_cast<int>(RayKind::kShadow)];
        }
      }
    }

    if (!any_bounce || depth >= options.max_depth) continue;
    if (features.reflection && mat.reflectivity > 0.0f) {
      const glm::vec3 tint = MaxChannel(mat.specular) > 0.0f ? mat.specular : glm::vec3(1.0f);
      const glm::vec3 wr = w * mat.reflectivity * tint;
      if (MaxChannel(wr) >= options.weight_cutoff) {
        glm::vec3 r = Reflect(d, ns);
        if (glm::dot(r, ng) <= 0.0f) r = Reflect(d, ng);  // shading normal bent it below
        PushRay(secondary, front, r, inf, pixel, wr, depth + 1, RayKind::kReflection);
        ++s.spawned[static_cast<int>(RayKind::kReflection)];
      } else {
        ++s.culled;
      }
    }
    if (features.transmission && mat.transmission > 0.0f) {
      const glm::vec3 wt = w * mat.transmission;
      if (MaxChannel(wt) >= options.weight_cutoff) {
        // Entering (the ray meets the face's front) goes from 1 into ior, leaving from ior.
        const float eta = entering ? 1.0f / mat.ior : mat.ior;
        // The shading normal must face the ray too, else refract about the geometric one.
        const glm::vec3 nr = glm::dot(d, ns) < 0.0f ? ns : ng;
        glm::vec3 t;
        bool through = Refract(d, nr, eta, &t);
        if (through && glm::dot(t, ng) >= 0.0f) through = Refract(d, ng, eta, &t);
        if (through) {
          PushRay(secondary, OffsetRayOrigin(p, -ng), t, inf, pixel, wt, depth + 1,
                  RayKind::kRefraction);
          ++s.spawned[static_cast<int>(RayKind::kRefraction)];
        } else {  // total internal reflection
          glm::vec3 r = Reflect(d, ns);
          if (glm::dot(r, ng) <= 0.0f) r = Reflect(d, ng);
          PushRay(secondary, front, r, inf, pixel, wt, depth + 1, RayKind::kReflection);
          ++s.spawned[static_cast<int>(RayKind::kReflection)];
        }
      } else {
        ++s.culled;
      }
    }
  }
  if (stats != nullptr) stats->Merge(s);
}

}  // namespace ref

void Shade(const Scene& scene, const ShadeOptions& options, const RayStreamView& rays,
           const HitStreamView& hits, Framebuffer& fb, RayStream& secondary, ShadeStats* stats) {
  ref::Shade(scene, options, rays, hits, fb, secondary, stats);
}

}  // namespace rs
