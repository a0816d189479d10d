// The job-kind table: every test here runs for every kind the proto's JobSpec oneof has, so a
// new kind is tested the day it is added.
#include <gtest/gtest.h>

#include <google/protobuf/descriptor.h>

#include <set>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"
#include "surfel/render/renderer.h"
#include "surfel/worker/job_kind.h"

namespace surfel::worker {
namespace {

std::string ValidationMessage(const v1::JobSpec& spec) {
    try {
        ValidateSpec(spec);
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument) << e.what();
        return e.what();
    }
    return "";
}

/// A spec whose oneof holds `kind`'s message with every field unset (proto reflection).
v1::JobSpec EmptySpec(const JobKind& kind) {
    v1::JobSpec spec;
    const google::protobuf::FieldDescriptor* field = v1::JobSpec::descriptor()->FindFieldByNumber(kind.Case());
    spec.GetReflection()->MutableMessage(&spec, field);
    return spec;
}

std::shared_ptr<const PointCloud> SmallSphere() {
    static const auto cloud = [] {
        ShapeOptions o;
        o.points = 2000;
        o.normals = true;
        return std::make_shared<const PointCloud>(SampleShape(Shape::kSphere, o));
    }();
    return cloud;
}

class EveryKind : public ::testing::TestWithParam<const JobKind*> {};

std::string KindName(const ::testing::TestParamInfo<const JobKind*>& info) { return std::string(info.param->Name()); }

INSTANTIATE_TEST_SUITE_P(JobKinds, EveryKind, ::testing::ValuesIn(JobKinds().begin(), JobKinds().end()), KindName);

TEST_P(EveryKind, IsFoundByItsCaseAndName) {
    const JobKind& kind = *GetParam();
    EXPECT_EQ(FindJobKind(kind.Case()), &kind);
    EXPECT_EQ(FindJobKind(kind.Name()), &kind);
    EXPECT_EQ(&KindOf(EmptySpec(kind)), &kind);
    EXPECT_FALSE(kind.Stage().empty());
    EXPECT_GE(kind.InputCount(EmptySpec(kind)), 1u);
    // The name is the oneof field's: Job.type, the CLI subcommand and the JSON key agree.
    EXPECT_EQ(v1::JobSpec::descriptor()->FindFieldByNumber(kind.Case())->name(), kind.Name());
}

TEST_P(EveryKind, AnEmptySpecNamesItsFirstCloudId) {
    const JobKind& kind = *GetParam();
    const v1::JobSpec spec = EmptySpec(kind);
    const std::vector<CloudInput> inputs = kind.Inputs(spec);
    ASSERT_EQ(inputs.size(), kind.InputCount(spec));
    EXPECT_EQ(ValidationMessage(spec), inputs[0].field + ": is required");
    EXPECT_EQ(inputs[0].field.rfind(std::string(kind.Name()) + ".", 0), 0u) << inputs[0].field;
}

TEST_P(EveryKind, SetInputFillsEachInput) {
    const JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "cloud" + std::to_string(i));
    const std::vector<CloudInput> inputs = kind.Inputs(spec);
    for (std::size_t i = 0; i < inputs.size(); ++i) EXPECT_EQ(inputs[i].id, "cloud" + std::to_string(i));
    EXPECT_EQ(ValidationMessage(spec), "");
}

TEST_P(EveryKind, ANegativeTimeoutIsRejected) {
    const JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "c");
    spec.set_timeout_ms(-1);
    EXPECT_EQ(ValidationMessage(spec), "timeout_ms: must be >= 0");
}

TEST_P(EveryKind, TheExampleRunsAndGivesItsResultType) {
    const JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "sphere");
    int loads = 0;
    double last_fraction = -1;
    const JobOutput out = RunJob(
        spec,
        [&](const std::string& id) {
            EXPECT_EQ(id, "sphere");
            ++loads;
            return SmallSphere();
        },
        [&](double f) {
            last_fraction = f;
            return true;
        });
    EXPECT_EQ(loads, 1) << "one load per distinct cloud id";
    EXPECT_GE(last_fraction, 0.0) << "progress is reported";
    EXPECT_EQ(std::pair(out.media_type, out.extension), kind.ResultType(spec));
    EXPECT_FALSE(out.bytes.empty());
    EXPECT_TRUE(out.report.contains("points"));
    EXPECT_TRUE(out.report.contains("time_ms"));
    EXPECT_EQ(out.report["points"].get<std::uint64_t>(), out.points);
    EXPECT_GE(out.time_ms, 0.0);
}

TEST_P(EveryKind, CancellationStopsTheRun) {
    const JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "sphere");
    try {
        RunJob(spec, [](const std::string&) { return SmallSphere(); }, [](double) { return false; });
        FAIL() << "a job whose progress hook says stop must not succeed";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kCancelled) << e.what();
    }
}

TEST(JobKindTable, ListsEveryOneofFieldOnceWithUniqueNames) {
    const google::protobuf::OneofDescriptor* oneof = v1::JobSpec::descriptor()->FindOneofByName("job");
    ASSERT_EQ(JobKinds().size(), static_cast<std::size_t>(oneof->field_count()));
    std::set<std::string_view> names;
    for (const JobKind* kind : JobKinds()) EXPECT_TRUE(names.insert(kind->Name()).second) << kind->Name();
    EXPECT_EQ(FindJobKind(v1::JobSpec::JOB_NOT_SET), nullptr);
    EXPECT_EQ(FindJobKind("no-such-kind"), nullptr);
}

TEST(JobKindTable, NoJobGivenListsTheKinds) {
    EXPECT_EQ(ValidationMessage(v1::JobSpec{}), "spec: no job given (" + JobKindNames() + ")");
    EXPECT_NE(JobKindNames().find("render"), std::string::npos);
    EXPECT_NE(JobKindNames().find("simplify"), std::string::npos);
}

// ---- Field paths of the core Options' validation, prefixed by the adapter -------------------

TEST(RenderJob, ValidationNamesTheField) {
    v1::JobSpec spec;
    spec.mutable_render()->set_cloud_id("c");
    EXPECT_EQ(ValidationMessage(spec), "");
    spec.mutable_render()->set_width(20000);
    EXPECT_EQ(ValidationMessage(spec), "render.width: must lie in 1..16384, got 20000");
    spec.mutable_render()->set_width(-3);
    EXPECT_EQ(ValidationMessage(spec), "render.width: must lie in 1..16384, got -3");
    spec.mutable_render()->set_width(10);
    spec.mutable_render()->set_samples_per_pixel(5000);
    EXPECT_EQ(ValidationMessage(spec), "render.samples_per_pixel: must lie in 1..1024, got 5000");
    spec.mutable_render()->set_samples_per_pixel(4);
    spec.mutable_render()->mutable_camera()->set_fovy_deg(180);
    EXPECT_EQ(ValidationMessage(spec), "render.camera.fovy_deg: must lie in 1..179, got 180");
    spec.mutable_render()->mutable_camera()->set_fovy_deg(0);  // 0 = the default
    EXPECT_EQ(ValidationMessage(spec), "");
    spec.mutable_render()->add_lights()->set_kind(v1::Light::DIRECTIONAL);
    EXPECT_EQ(ValidationMessage(spec), "render.lights[0].vector: a directional light needs a non-zero direction");
    spec.mutable_render()->mutable_lights(0)->mutable_vector()->set_z(-1);
    spec.mutable_render()->mutable_lights(0)->set_intensity(-2);
    EXPECT_EQ(ValidationMessage(spec), "render.lights[0].intensity: must lie in 0..1e+06, got -2");
    spec.mutable_render()->mutable_lights(0)->set_intensity(1);
    spec.mutable_render()->mutable_lights(0)->set_kind(static_cast<v1::Light::Kind>(7));
    EXPECT_EQ(ValidationMessage(spec), "render.lights[0].kind: unknown kind 7");
    spec.mutable_render()->mutable_lights(0)->set_kind(v1::Light::KIND_UNSPECIFIED);  // = directional
    EXPECT_EQ(ValidationMessage(spec), "");
    spec.mutable_render()->set_format(static_cast<v1::RenderJob::Format>(9));
    EXPECT_EQ(ValidationMessage(spec), "render.format: unknown format 9");
    spec.mutable_render()->set_format(v1::RenderJob::PNG);
    spec.mutable_render()->set_max_iterations(5000);
    EXPECT_EQ(ValidationMessage(spec), "render.max_iterations: must lie in 1..1000, got 5000");
    spec.mutable_render()->set_max_iterations(0);
    // Eye alone is fine (the target frames the cloud); eye and target equal are not.
    *spec.mutable_render()->mutable_camera()->mutable_eye() = ToProto(Vec3d(0, 0, 0));
    EXPECT_EQ(ValidationMessage(spec), "");
    *spec.mutable_render()->mutable_camera()->mutable_target() = ToProto(Vec3d(0, 0, 0));
    EXPECT_EQ(ValidationMessage(spec), "render.camera: eye and target must differ");
}

TEST(RenderJob, QualityIsCheckedAndReachesTheRenderWithTheExplicitFieldsOverridingIt) {
    v1::JobSpec spec;
    spec.mutable_render()->set_cloud_id("c");
    spec.mutable_render()->set_quality(static_cast<v1::RenderJob::Quality>(5));
    EXPECT_EQ(ValidationMessage(spec), "render.quality: unknown quality 5");
    v1::RenderJob& r = *spec.mutable_render();
    r.set_width(12);
    r.set_height(10);
    auto run = [&] { return RunJob(spec, [](const std::string&) { return SmallSphere(); }).report; };
    r.set_quality(v1::RenderJob::QUALITY_UNSPECIFIED);
    const nlohmann::json unspecified = run();
    r.set_quality(v1::RenderJob::FULL);
    const nlohmann::json full = run();
    r.set_quality(v1::RenderJob::PREVIEW);
    const nlohmann::json preview = run();
    EXPECT_EQ(unspecified["quality"], "full");
    EXPECT_EQ(full["quality"], "full");
    EXPECT_EQ(preview["quality"], "preview");
    // The acceptance: 1e-3 h at full quality, kPreviewRelativePrecision h at preview (h is the one
    // scale at both: the sphere is evenly sampled).
    const double h = full["h"].get<double>();
    EXPECT_NEAR(full["precision"].get<double>(), 1e-3 * h, 1e-6 * h);
    EXPECT_NEAR(unspecified["precision"].get<double>(), 1e-3 * h, 1e-6 * h);
    EXPECT_NEAR(preview["precision"].get<double>(), kPreviewRelativePrecision * preview["h"].get<double>(), 1e-6 * h);
    // An explicit precision overrides the preset's.
    r.set_precision(2e-4 * h);
    EXPECT_NEAR(run()["precision"].get<double>(), 2e-4 * h, 1e-6 * h);
}

TEST(SimplifyJob, ValidationNamesTheField) {
    v1::JobSpec s;
    s.mutable_simplify()->set_cloud_id("c");
    EXPECT_EQ(ValidationMessage(s), "");  // hierarchical with its own bound (n_max)
    s.mutable_simplify()->set_method(v1::SimplifyJob::PARTICLE);
    EXPECT_EQ(ValidationMessage(s), "simplify.target: is required for this method");
    s.mutable_simplify()->set_error(0.1);
    EXPECT_EQ(ValidationMessage(s), "simplify.error: this method takes a target, not an error bound");
    s.mutable_simplify()->set_target(10);
    EXPECT_EQ(ValidationMessage(s), "simplify.target: give target or error, not both");
    s.mutable_simplify()->clear_error();
    s.mutable_simplify()->set_max_variation(2);
    EXPECT_EQ(ValidationMessage(s).rfind("simplify.max_variation: must lie in ", 0), 0u) << ValidationMessage(s);
    s.mutable_simplify()->clear_max_variation();
    s.mutable_simplify()->set_method(static_cast<v1::SimplifyJob::Method>(42));
    EXPECT_EQ(ValidationMessage(s), "simplify.method: unknown method 42");
    s.mutable_simplify()->set_method(v1::SimplifyJob::METHOD_UNSPECIFIED);  // = hierarchical
    EXPECT_EQ(ValidationMessage(s), "");
    s.mutable_simplify()->set_representative(v1::SimplifyJob::MEMBER);
    EXPECT_EQ(ValidationMessage(s), "");
    s.mutable_simplify()->set_method(v1::SimplifyJob::PARTICLE);
    s.mutable_simplify()->set_target(10);
    EXPECT_EQ(ValidationMessage(s),
              "simplify.representative: particle simulation places its own points; member is for hierarchical, "
              "incremental, iterative and voxel");
    s.mutable_simplify()->set_representative(static_cast<v1::SimplifyJob::Representative>(9));
    EXPECT_EQ(ValidationMessage(s), "simplify.representative: unknown representative 9");
    s.mutable_simplify()->clear_representative();
    s.mutable_simplify()->clear_target();
    s.mutable_simplify()->set_method(v1::SimplifyJob::METHOD_UNSPECIFIED);
    s.mutable_simplify()->clear_cloud_id();
    EXPECT_EQ(ValidationMessage(s), "simplify.cloud_id: is required");
}

TEST(ResampleJob, ValidationNamesTheField) {
    v1::JobSpec s;
    s.mutable_resample()->set_cloud_id("c");
    EXPECT_EQ(ValidationMessage(s), "resample.target: give target or spacing");
    s.mutable_resample()->set_target(100);
    EXPECT_EQ(ValidationMessage(s), "");
    s.mutable_resample()->set_spacing(0.1);
    EXPECT_EQ(ValidationMessage(s), "resample.target: give target or spacing, not both");
    s.mutable_resample()->set_target(0);
    s.mutable_resample()->set_spacing(-1);
    EXPECT_EQ(ValidationMessage(s), "resample.spacing: must be positive, got -1");
    s.mutable_resample()->set_spacing(0.1);
    s.mutable_resample()->set_iterations(5000);
    EXPECT_EQ(ValidationMessage(s), "resample.iterations: must lie in 0..1000, got 5000");
    s.mutable_resample()->set_iterations(0);  // = the default
    s.mutable_resample()->set_method(static_cast<v1::ResampleJob::Method>(9));
    EXPECT_EQ(ValidationMessage(s), "resample.method: unknown method 9");
}

TEST(ResampleJob, AnInputTooSmallForKeepInputNamesTheField) {
    v1::JobSpec spec;
    spec.mutable_resample()->set_cloud_id("sphere");
    spec.mutable_resample()->set_target(100);
    spec.mutable_resample()->set_keep_input(true);
    try {
        RunJob(spec, [](const std::string&) { return SmallSphere(); });
        FAIL() << "keep_input with fewer points than the input must fail";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_EQ(std::string(e.what()).rfind("resample.target: with keep_input must exceed the input's 2000 points", 0), 0u)
            << e.what();
    }
}

TEST(BooleanJob, ValidationNamesTheField) {
    v1::JobSpec s;
    s.mutable_boolean()->set_cloud_id_a("a");
    EXPECT_EQ(ValidationMessage(s), "boolean.cloud_id_b: is required");
    s.mutable_boolean()->set_cloud_id_b("b");
    EXPECT_EQ(ValidationMessage(s).rfind("boolean.op: is required", 0), 0u) << ValidationMessage(s);
    s.mutable_boolean()->set_op(static_cast<v1::BooleanJob::Op>(11));
    EXPECT_EQ(ValidationMessage(s), "boolean.op: unknown operation 11");
    s.mutable_boolean()->set_op(v1::BooleanJob::DIFFERENCE);
    EXPECT_EQ(ValidationMessage(s), "");
    v1::Similarity& t = *s.mutable_boolean()->mutable_transform_b();
    t.set_scale(-2);
    EXPECT_EQ(ValidationMessage(s), "boolean.transform_b.scale: must lie in 1e-06..1e+06, got -2");
    t.set_scale(0);  // = 1
    t.add_rotation(1);
    EXPECT_EQ(ValidationMessage(s).rfind("boolean.transform_b.rotation: must have 9 numbers", 0), 0u)
        << ValidationMessage(s);
    for (int i = 1; i < 9; ++i) t.add_rotation(i == 4 || i == 8 ? 1 : 0);
    EXPECT_EQ(ValidationMessage(s), "");  // the identity, row-major
    t.set_rotation(0, 2);                 // not orthonormal
    EXPECT_EQ(ValidationMessage(s).rfind("boolean.transform_b.rotation: ", 0), 0u) << ValidationMessage(s);
    s.mutable_boolean()->clear_transform_b();
    s.mutable_boolean()->set_blend_radius(-0.5);
    EXPECT_EQ(ValidationMessage(s), "boolean.blend_radius: must be finite and at least 0, got -0.5");
    s.mutable_boolean()->set_blend_radius(0.01);
    s.mutable_boolean()->set_blend_iterations(20000);
    EXPECT_EQ(ValidationMessage(s), "boolean.blend_iterations: must lie in 1..10000, got 10001");
    s.mutable_boolean()->set_blend_iterations(0);  // = 200
    EXPECT_EQ(ValidationMessage(s), "");
}

TEST(BooleanJob, TwoInputsOfOneCloudAreLoadedOnce) {
    v1::JobSpec spec = KindOf([] {
                           v1::JobSpec s;
                           s.mutable_boolean();
                           return s;
                       }())
                           .Example();
    spec.mutable_boolean()->set_cloud_id_a("sphere");
    spec.mutable_boolean()->set_cloud_id_b("sphere");
    int loads = 0;
    const JobOutput out = RunJob(spec, [&](const std::string&) {
        ++loads;
        return SmallSphere();
    });
    EXPECT_EQ(loads, 1);
    EXPECT_GT(out.report["curve_samples"].get<int>(), 0) << out.report.dump();
    const PointCloud result = ParsePly(out.bytes, "result");
    EXPECT_EQ(result.size(), out.points);
}

TEST(SimplifyJob, ProducesAPlyWithTheTargetCount) {
    ShapeOptions o;
    o.points = 5000;
    const auto sphere = std::make_shared<const PointCloud>(SampleShape(Shape::kSphere, o));
    v1::JobSpec spec;
    spec.mutable_simplify()->set_cloud_id("sphere");
    spec.mutable_simplify()->set_target(400);
    const JobOutput out = RunJob(spec, [&](const std::string& id) {
        EXPECT_EQ(id, "sphere");
        return sphere;
    });
    EXPECT_EQ(out.media_type, "application/ply");
    const PointCloud result = ParsePly(out.bytes, "result");
    EXPECT_EQ(result.size(), 400u);
    EXPECT_EQ(out.report["points"], 400);
    EXPECT_TRUE(out.report.contains("error"));
}

}  // namespace
}  // namespace surfel::worker
