// Scene model functions: mesh view, bounds, camera-path interpolation, features and validation.
// Validation is the single place that turns a malformed scene into an rs::Error naming the
// element, so every loader (and hand-built scenes) get the same checks.
#include "scenes/scene.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "scenes/scene_internal.h"

namespace rs {

static_assert(sizeof(glm::vec3) == 3 * sizeof(float), "MeshView needs packed positions");
static_assert(sizeof(glm::uvec3) == 3 * sizeof(uint32_t), "MeshView needs packed indices");

MeshView Scene::mesh() const {
  MeshView view;
  view.positions = positions.empty() ? nullptr : &positions[0].x;
  view.num_vertices = positions.size();
  view.stride = 3;
  view.indices = triangles.empty() ? nullptr : &triangles[0].x;
  view.num_triangles = triangles.size();
  return view;
}

void Scene::Bounds(glm::vec3& lo, glm::vec3& hi) const {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  lo = glm::vec3(kInf);
  hi = glm::vec3(-kInf);
  for (const glm::vec3& p : positions) {
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
    lo = glm::min(lo, p);
    hi = glm::max(hi, p);
  }
  if (lo.x > hi.x) {  // no (finite) vertex
    lo = glm::vec3(0.0f);
    hi = glm::vec3(0.0f);
  }
}

Camera CameraPath::At(int frame, float speed, const Camera& fallback) const {
  if (keys.empty()) return fallback;
  if (keys.size() == 1 || frames <= 1) return keys[0];
  // Path time in frames, clamped to [0, frames - 1]; NaN speed counts as time 0.
  const double last = static_cast<double>(frames - 1);
  double t = static_cast<double>(frame) * static_cast<double>(speed);
  if (!(t > 0.0)) t = 0.0;
  if (t > last) t = last;
  // Keys are spread evenly over the path: key k sits at time k * last / (keys - 1).
  const double u = t / last * static_cast<double>(keys.size() - 1);
  const size_t i = std::min(static_cast<size_t>(u), keys.size() - 2);
  const float f = static_cast<float>(u - static_cast<double>(i));
  const Camera& a = keys[i];
  const Camera& b = keys[i + 1];
  Camera c = a;
  c.eye = a.eye + (b.eye - a.eye) * f;
  c.look_at = a.look_at + (b.look_at - a.look_at) * f;
  const glm::vec3 up = a.up + (b.up - a.up) * f;
  if (glm::dot(up, up) > 1e-12f) c.up = up;  // opposite ups: keep a's
  c.fov_y_deg = a.fov_y_deg + (b.fov_y_deg - a.fov_y_deg) * f;
  return c;
}

void NormalizeScale(Scene& scene) {
  const std::string& label = scene.source.empty() ? scene.name : scene.source;
  float m = 0.0f;
  const auto take = [&m](const glm::vec3& p) {
    for (int a = 0; a < 3; ++a) m = std::fmax(m, std::fabs(p[a]));  // fmax drops NaN: checked
  };
  for (const glm::vec3& p : scene.positions) take(p);
  for (const PointLight& l : scene.lights) take(l.position);
  take(scene.camera.eye);
  take(scene.camera.look_at);
  for (const Camera& c : scene.path.keys) {
    take(c.eye);
    take(c.look_at);
  }
  if (!(m >= kMinSceneMagnitude && m <= kMaxSceneMagnitude)) {
    detail::Fail("{}: largest coordinate magnitude {} outside the supported range [{}, {}]",
                 label, m, kMinSceneMagnitude, kMaxSceneMagnitude);
  }
  if (m >= std::ldexp(1.0f, -20) && m <= std::ldexp(1.0f, 20)) return;
  const int e = std::ilogb(m);  // m in [2^e, 2^(e + 1))
  const auto scale = [e](glm::vec3& p) {
    for (int a = 0; a < 3; ++a) p[a] = std::ldexp(p[a], -e);
  };
  for (glm::vec3& p : scene.positions) scale(p);
  for (PointLight& l : scene.lights) {
    scale(l.position);
    l.falloff = std::ldexp(l.falloff, 2 * e);
  }
  scale(scene.camera.eye);
  scale(scene.camera.look_at);
  for (Camera& c : scene.path.keys) {
    scale(c.eye);
    scale(c.look_at);
  }
  scene.coordinate_scale = std::ldexp(scene.coordinate_scale, -e);
}

SceneFeatures ComputeFeatures(const Scene& scene) {
  SceneFeatures features;
  features.lights = !scene.lights.empty();
  features.triangles = scene.triangles.size();
  features.large = features.triangles > kLargeSceneTriangles;
  // Only materials some triangle uses count: an MTL may define many unused ones.
  std::vector<char> used(scene.materials.size(), 0);
  for (const uint32_t id : scene.material_ids) {
    if (id < used.size()) used[id] = 1;
  }
  for (size_t m = 0; m < scene.materials.size(); ++m) {
    if (!used[m]) continue;
    const Material& mat = scene.materials[m];
    const float ks = std::max({mat.specular.x, mat.specular.y, mat.specular.z});
    if (ks > 0.0f && mat.shininess > 0.0f) features.specular = true;
    if (mat.reflectivity > 0.0f) features.reflection = true;
    if (mat.transmission > 0.0f) features.transmission = true;
    if (mat.texture >= 0 && static_cast<size_t>(mat.texture) < scene.textures.size() &&
        !scene.uvs.empty()) {
      features.textures = true;
    }
  }
  return features;
}

namespace {

bool Finite(const glm::vec3& v) {
  return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}

std::string Str(const glm::vec3& v) { return fmt::format("({}, {}, {})", v.x, v.y, v.z); }

void CheckCamera(const Camera& c, const std::string& label, const std::string& what) {
  using detail::Fail;
  if (!Finite(c.eye) || !Finite(c.look_at) || !Finite(c.up) || !std::isfinite(c.fov_y_deg)) {
    Fail("{}: {}: non-finite value (eye {}, look_at {}, up {}, fov {})", label, what, Str(c.eye),
         Str(c.look_at), Str(c.up), c.fov_y_deg);
  }
  const glm::vec3 dir = c.look_at - c.eye;
  if (glm::dot(dir, dir) <= 0.0f) Fail("{}: {}: eye equals look_at {}", label, what, Str(c.eye));
  const glm::vec3 side = glm::cross(glm::normalize(dir), c.up);
  if (!(glm::dot(side, side) > 1e-12f)) {
    Fail("{}: {}: up {} is zero or parallel to the view direction", label, what, Str(c.up));
  }
  if (!(c.fov_y_deg > 0.0f && c.fov_y_deg < 180.0f)) {
    Fail("{}: {}: fov {} outside (0, 180) degrees", label, what, c.fov_y_deg);
  }
}

}  // namespace

namespace detail {

void ValidateSceneAs(const Scene& scene, const std::string& label) {
  const size_t nv = scene.positions.size();
  for (size_t i = 0; i < nv; ++i) {
    const glm::vec3& p = scene.positions[i];
    if (!Finite(p)) Fail("{}: vertex {}: position {} is not finite", label, i, Str(p));
    if (std::max({std::fabs(p.x), std::fabs(p.y), std::fabs(p.z)}) > kMaxCoordinate) {
      Fail("{}: vertex {}: position {} too large (limit {})", label, i, Str(p), kMaxCoordinate);
    }
  }
  if (scene.materials.empty()) Fail("{}: scene has no materials", label);
  if (scene.material_ids.size() != scene.triangles.size()) {
    Fail("{}: {} material ids for {} triangles (need one per triangle)", label,
         scene.material_ids.size(), scene.triangles.size());
  }
  for (size_t t = 0; t < scene.triangles.size(); ++t) {
    const glm::uvec3& tri = scene.triangles[t];
    for (int k = 0; k < 3; ++k) {
      if (tri[k] >= nv) {
        Fail("{}: triangle {}: vertex index {} out of range ({} vertices)", label, t, tri[k], nv);
      }
    }
    if (scene.material_ids[t] >= scene.materials.size()) {
      Fail("{}: triangle {}: material id {} out of range ({} materials)", label, t,
           scene.material_ids[t], scene.materials.size());
    }
  }
  if (!scene.uvs.empty() && scene.uvs.size() != nv) {
    Fail("{}: {} uvs for {} vertices (need none or one per vertex)", label, scene.uvs.size(), nv);
  }
  for (size_t i = 0; i < scene.uvs.size(); ++i) {
    const glm::vec2& uv = scene.uvs[i];
    if (!std::isfinite(uv.x) || !std::isfinite(uv.y)) {
      Fail("{}: vertex {}: uv ({}, {}) is not finite", label, i, uv.x, uv.y);
    }
  }
  if (!scene.normals.empty() && scene.normals.size() != nv) {
    Fail("{}: {} normals for {} vertices (need none or one per vertex)", label,
         scene.normals.size(), nv);
  }
  for (size_t i = 0; i < scene.normals.size(); ++i) {
    if (!Finite(scene.normals[i])) {
      Fail("{}: vertex {}: normal {} is not finite", label, i, Str(scene.normals[i]));
    }
  }
  for (size_t m = 0; m < scene.materials.size(); ++m) {
    const Material& mat = scene.materials[m];
    const std::string what = fmt::format("material {} ('{}')", m, mat.name);
    if (!Finite(mat.diffuse) || !Finite(mat.specular) || !std::isfinite(mat.shininess) ||
        !std::isfinite(mat.reflectivity) || !std::isfinite(mat.transmission) ||
        !std::isfinite(mat.ior)) {
      Fail("{}: {}: non-finite value", label, what);
    }
    if (std::min({mat.diffuse.x, mat.diffuse.y, mat.diffuse.z, mat.specular.x, mat.specular.y,
                  mat.specular.z}) < 0.0f) {
      Fail("{}: {}: negative colour", label, what);
    }
    if (mat.shininess < 0.0f) Fail("{}: {}: shininess {} < 0", label, what, mat.shininess);
    if (mat.reflectivity < 0.0f || mat.reflectivity > 1.0f) {
      Fail("{}: {}: reflectivity {} outside [0, 1]", label, what, mat.reflectivity);
    }
    if (mat.transmission < 0.0f || mat.transmission > 1.0f) {
      Fail("{}: {}: transmission {} outside [0, 1]", label, what, mat.transmission);
    }
    if (!(mat.ior > 0.0f)) Fail("{}: {}: ior {} must be > 0", label, what, mat.ior);
    if (mat.texture < -1 ||
        (mat.texture >= 0 && static_cast<size_t>(mat.texture) >= scene.textures.size())) {
      Fail("{}: {}: texture index {} out of range ({} textures)", label, what, mat.texture,
           scene.textures.size());
    }
  }
  for (size_t i = 0; i < scene.textures.size(); ++i) {
    const Texture& tex = scene.textures[i];
    if (tex.width <= 0 || tex.height <= 0) {
      Fail("{}: texture {} ('{}'): size {}x{} is empty", label, i, tex.path, tex.width, tex.height);
    }
    const size_t expected = static_cast<size_t>(tex.width) * static_cast<size_t>(tex.height) * 3;
    if (tex.rgb.size() != expected) {
      Fail("{}: texture {} ('{}'): {} floats for {}x{} rgb pixels (expected {})", label, i,
           tex.path, tex.rgb.size(), tex.width, tex.height, expected);
    }
    for (size_t k = 0; k < tex.rgb.size(); ++k) {
      if (!std::isfinite(tex.rgb[k])) {
        Fail("{}: texture {} ('{}'): pixel {} is not finite", label, i, tex.path, k / 3);
      }
    }
  }
  for (size_t i = 0; i < scene.lights.size(); ++i) {
    const PointLight& light = scene.lights[i];
    if (!Finite(light.position) || !Finite(light.color) || !std::isfinite(light.falloff)) {
      Fail("{}: light {}: non-finite value", label, i);
    }
    if (std::min({light.color.x, light.color.y, light.color.z}) < 0.0f) {
      Fail("{}: light {}: negative colour {}", label, i, Str(light.color));
    }
    if (light.falloff < 0.0f) Fail("{}: light {}: falloff {} < 0", label, i, light.falloff);
  }
  CheckCamera(scene.camera, label, "camera");
  for (size_t k = 0; k < scene.path.keys.size(); ++k) {
    CheckCamera(scene.path.keys[k], label, fmt::format("path key {}", k));
  }
  if (scene.path.frames < 1) Fail("{}: path: frames {} < 1", label, scene.path.frames);
  // Between two keys the view direction is interpolated linearly: d(f) = da + f (db - da). If
  // it (nearly) vanishes for some f in [0, 1], the eye meets look_at at that frame. Checked at
  // load time, so no frame is rendered (and written) before the bad one.
  const std::vector<Camera>& keys = scene.path.keys;
  for (size_t k = 0; k + 1 < keys.size() && scene.path.frames > 1; ++k) {
    const glm::dvec3 da(keys[k].look_at - keys[k].eye);
    const glm::dvec3 db(keys[k + 1].look_at - keys[k + 1].eye);
    const glm::dvec3 dd = db - da;
    const double dd2 = glm::dot(dd, dd);
    const double f = dd2 > 0.0 ? std::clamp(-glm::dot(da, dd) / dd2, 0.0, 1.0) : 0.0;
    const glm::dvec3 d = da + f * dd;
    const double scale = std::max(glm::dot(da, da), glm::dot(db, db));
    if (glm::dot(d, d) <= 1e-10 * scale) {
      const double frame = (static_cast<double>(k) + f) *
                           static_cast<double>(scene.path.frames - 1) /
                           static_cast<double>(keys.size() - 1);
      Fail("{}: path keys {} and {}: the eye meets look_at between them (frame {:.0f} at speed 1)",
           label, k, k + 1, frame);
    }
  }
  if (!Finite(scene.background)) Fail("{}: background is not finite", label);
  if (!std::isfinite(scene.ambient) || scene.ambient < 0.0f) {
    Fail("{}: ambient {} must be finite and >= 0", label, scene.ambient);
  }
}

}  // namespace detail

void ValidateScene(const Scene& scene) {
  detail::ValidateSceneAs(scene, scene.source.empty()
                                     ? (scene.name.empty() ? std::string("scene") : scene.name)
                                     : scene.source);
}

}  // namespace rs
