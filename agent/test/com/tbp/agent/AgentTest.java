package com.tbp.agent;

import static org.junit.Assert.assertArrayEquals;
import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertFalse;
import static org.junit.Assert.assertTrue;

import java.io.File;
import java.io.IOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.util.Arrays;
import java.util.List;
import java.util.Map;
import java.util.Random;
import org.junit.Before;
import org.junit.Test;

/** The protocol core against bad input and a misbehaving camera: error answers, never a dead agent. */
public class AgentTest {

    private Fakes.Camera camera;
    private Fakes.Disk disk;
    private Fakes.Recorder log;
    private File folder;
    private Agent agent;
    private Fakes.Client client;

    @Before
    public void setUp() throws IOException {
        camera = new Fakes.Camera();
        disk = new Fakes.Disk();
        log = new Fakes.Recorder();
        folder = Fakes.folder();
        ImageStore store = new ImageStore(folder, disk);
        store.open();
        agent = new Agent(camera, store, log);
        client = new Fakes.Client();
        agent.opened(client);
    }

    private List<Map<String, Object>> send(String text) {
        byte[] bytes = text.getBytes(StandardCharsets.UTF_8);
        agent.received(client, bytes, 0, bytes.length);
        agent.runPending();
        return client.take();
    }

    private void sendBytes(byte[] bytes) {
        agent.received(client, bytes, 0, bytes.length);
        agent.runPending();
    }

    private static Map<String, Object> only(List<Map<String, Object>> answers) {
        assertEquals(answers.toString(), 1, answers.size());
        return answers.get(0);
    }

    @SuppressWarnings("unchecked")
    private static String code(Map<String, Object> answer) {
        assertEquals(Boolean.FALSE, answer.get("ok"));
        return (String) ((Map<String, Object>) answer.get("error")).get("code");
    }

    private void assertAlive() {
        Map<String, Object> hello = only(send("{\"id\": 999, \"op\": \"hello\", \"version\": 1}\n"));
        assertEquals(999L, hello.get("id"));
        assertEquals(Boolean.TRUE, hello.get("ok"));
    }

    @Test
    public void helloReportsTheCameraAndIgnoresUnknownFields() {
        Map<String, Object> hello = only(send("{\"id\":1,\"op\":\"hello\",\"version\":1,\"future\":{\"x\":[1]}}\n"));
        assertEquals(1L, hello.get("agent_version"));
        assertEquals("FAKE0001", hello.get("serial"));
        assertEquals("Fake Phone", hello.get("model"));
        assertEquals(10.0, hello.get("min_focus_diopters"));
        assertEquals(1L, hello.get("focus_distance_calibration"));
        assertEquals("realtime", hello.get("timestamp_source"));
        assertEquals(0.002, hello.get("exposure_s"));
        assertEquals(50L, hello.get("iso"));
        assertEquals(64L, hello.get("image_width"));
        assertEquals(48L, hello.get("image_height"));
    }

    @Test
    public void malformedLinesAreBadRequestsWithIdZero() {
        String[] bad = {"not json\n", "[1, 2]\n", "\"text\"\n", "{\"op\": \"hello\"}\n", "{\"id\": -1, \"op\": \"hello\"}\n",
            "{\"id\": 9007199254740992, \"op\": \"hello\"}\n", "{\"id\": 1.0, \"op\": \"hello\"}\n",
            "{\"id\": true, \"op\": \"hello\"}\n", "{\"id\": \"1\", \"op\": \"hello\"}\n", "{\"id\": 1}\n",
            "{\"id\": 1, \"op\": 5}\n", "{\"id\": 1, \"op\": \"hello\", \"x\": NaN}\n", "\n", "{\"id\": 1,}\n"};
        for (String line : bad) {
            Map<String, Object> answer = only(send(line));
            assertEquals(line, 0L, answer.get("id"));
            assertEquals(line, "BAD_REQUEST", code(answer));
        }
        sendBytes(new byte[] {'{', (byte) 0xff, (byte) 0xfe, '}', '\n'});
        assertEquals("BAD_REQUEST", code(only(client.take())));
        assertAlive();
    }

    @Test
    public void aLineOverSixtyFourKibibytesIsRefusedAndTheNextIsRead() {
        char[] filler = new char[Agent.MAX_LINE];
        Arrays.fill(filler, ' ');
        String tooLong = "{\"id\": 5, \"op\": \"hello\"}" + new String(filler) + "\n";
        Map<String, Object> answer = only(send(tooLong));
        assertEquals(0L, answer.get("id"));
        assertEquals("BAD_REQUEST", code(answer));
        String justFits = "{\"id\": 6, \"op\": \"hello\"}";
        justFits = justFits + new String(filler, 0, Agent.MAX_LINE - justFits.length() - 1) + "\n";
        assertEquals(6L, only(send(justFits)).get("id"));
        assertAlive();
    }

    @SuppressWarnings("unchecked")
    private static String message(Map<String, Object> answer) {
        assertEquals(Boolean.FALSE, answer.get("ok"));
        return (String) ((Map<String, Object>) answer.get("error")).get("message");
    }

    @Test
    public void aCaptureSettingOutsideTheSensorNamesTheSettingAndTheRange() {
        assertEquals("capture: exposure_s 5.0 outside the sensor's [1.0E-5, 0.5] s",
                message(only(send("{\"id\": 8, \"op\": \"capture\", \"exposure_s\": 5}\n"))));
        assertEquals("capture: iso 10 outside the sensor's [50, 3200]",
                message(only(send("{\"id\": 9, \"op\": \"capture\", \"iso\": 10}\n"))));
        assertTrue(camera.captures.isEmpty());
    }

    @Test
    public void unknownOpsAndBadFieldsNameTheRequest() {
        Map<String, Object> answer = only(send("{\"id\": 7, \"op\": \"reboot\"}\n"));
        assertEquals(7L, answer.get("id"));
        assertEquals("UNKNOWN_OP", code(answer));
        String[] bad = {"{\"id\": 8, \"op\": \"focus\"}\n", "{\"id\": 8, \"op\": \"focus\", \"diopters\": \"2\"}\n",
            "{\"id\": 8, \"op\": \"focus\", \"diopters\": true}\n", "{\"id\": 8, \"op\": \"focus\", \"diopters\": 1e400}\n",
            "{\"id\": 8, \"op\": \"capture\", \"exposure_s\": null}\n", "{\"id\": 8, \"op\": \"capture\", \"exposure_s\": 5}\n",
            "{\"id\": 8, \"op\": \"capture\", \"iso\": 100.5}\n", "{\"id\": 8, \"op\": \"capture\", \"iso\": 10}\n",
            "{\"id\": 8, \"op\": \"delete\"}\n", "{\"id\": 8, \"op\": \"delete\", \"path\": 3}\n"};
        for (String line : bad) {
            answer = only(send(line));
            assertEquals(line, 8L, answer.get("id"));
            assertEquals(line, "BAD_REQUEST", code(answer));
        }
        assertTrue(camera.focuses.isEmpty() && camera.captures.isEmpty());
        assertAlive();
    }

    @Test
    public void focusOutsideTheLensRangeIsRefusedBeforeTheCamera() {
        assertEquals("FOCUS_OUT_OF_RANGE", code(only(send("{\"id\": 2, \"op\": \"focus\", \"diopters\": 10.5}\n"))));
        assertEquals("FOCUS_OUT_OF_RANGE", code(only(send("{\"id\": 3, \"op\": \"focus\", \"diopters\": -0.1}\n"))));
        assertTrue(camera.focuses.isEmpty());
        assertTrue(send("{\"id\": 4, \"op\": \"focus\", \"diopters\": 10}\n").isEmpty());
        camera.focuses.poll().ok(new CameraBackend.Focused(9.98, 77L));
        agent.runPending();
        Map<String, Object> done = only(client.take());
        assertEquals(Boolean.TRUE, done.get("ok"));
        assertEquals(9.98, done.get("diopters"));
        assertEquals(0L, done.get("lens_state"));
        assertEquals(77L, done.get("stationary_at_ns"));
    }

    @Test
    public void cameraOperationsRunOneAtATimeInArrivalOrderWhileOthersAnswerAtOnce() throws IOException {
        assertTrue(send("{\"id\": 1, \"op\": \"focus\", \"diopters\": 2.2}\n").isEmpty());
        assertTrue(send("{\"id\": 2, \"op\": \"capture\"}\n{\"id\": 3, \"op\": \"capture\", \"exposure_s\": 0.01,"
                + " \"iso\": 400}\n").isEmpty());
        assertEquals(1, camera.focuses.size());
        assertEquals(0, camera.captures.size());  // waits for the focus
        Map<String, Object> clock = only(send("{\"id\": 4, \"op\": \"clock\"}\n"));
        assertEquals(4L, clock.get("id"));
        assertEquals(camera.clockNs, clock.get("device_ns"));

        camera.focuses.poll().ok(new CameraBackend.Focused(2.2, 10L));
        agent.runPending();
        assertEquals(1L, only(client.take()).get("id"));
        assertEquals(1, camera.captures.size());  // the first capture, not yet the second

        Fakes.FakeStill first = camera.answerCapture(5000);
        agent.runPending();
        Map<String, Object> shot = only(client.take());
        assertEquals(2L, shot.get("id"));
        assertEquals("/sdcard/DCIM/tbp/IMG_00000.jpg", shot.get("path"));
        assertEquals(5000L, shot.get("size"));
        assertEquals(first.sensorTimestampNs, shot.get("sensor_timestamp_ns"));
        assertEquals(2.5, shot.get("focus_diopters"));
        assertEquals(1, first.releases);
        assertArrayEquals(first.bytes, Files.readAllBytes(new File(folder, "IMG_00000.jpg").toPath()));

        assertArrayEquals(new double[] {0.01, 400}, camera.captureSettings.pollLast(), 0);
        camera.answerCapture(10);
        agent.runPending();
        assertEquals("/sdcard/DCIM/tbp/IMG_00001.jpg", only(client.take()).get("path"));
    }

    @Test
    public void aFullCameraQueueAnswersCameraBusy() {
        for (int id = 1; id <= Agent.CAMERA_QUEUE_LIMIT; id++) {
            assertTrue(send("{\"id\": " + id + ", \"op\": \"capture\"}\n").isEmpty());
        }
        Map<String, Object> busy = only(send("{\"id\": 100, \"op\": \"capture\"}\n"));
        assertEquals(100L, busy.get("id"));
        assertEquals("CAMERA_BUSY", code(busy));
        camera.answerCapture(10);
        agent.runPending();
        assertEquals(1L, only(client.take()).get("id"));
        assertTrue(send("{\"id\": 101, \"op\": \"focus\", \"diopters\": 1}\n").isEmpty());  // room again
    }

    @Test
    public void deletesOnlyFilesDirectlyInTheImageFolder() throws IOException {
        File outside = new File(folder.getParentFile(), "keep.jpg");
        Files.write(outside.toPath(), new byte[] {1});
        Files.write(new File(folder, "IMG_00003.jpg").toPath(), new byte[] {1});
        String[] refused = {"/sdcard/DCIM/tbp/../keep.jpg", "/sdcard/DCIM/keep.jpg", "/sdcard/DCIM/tbp/",
            "/sdcard/DCIM/tbp/.", "/sdcard/DCIM/tbp/..", "/sdcard/DCIM/tbp/sub/x.jpg", "sdcard/DCIM/tbp/IMG_00003.jpg",
            "/sdcard/DCIM/tbpx/IMG_00003.jpg", "/sdcard/DCIM/tbp/IMG\\u0000.jpg"};
        for (String path : refused) {
            Map<String, Object> answer = only(send("{\"id\": 5, \"op\": \"delete\", \"path\": \"" + path + "\"}\n"));
            assertEquals(path, "BAD_REQUEST", code(answer));
        }
        assertTrue(outside.exists());
        assertEquals("NOT_FOUND", code(only(send(
                "{\"id\": 6, \"op\": \"delete\", \"path\": \"/sdcard/DCIM/tbp/IMG_00009.jpg\"}\n"))));
        Map<String, Object> ok = only(send("{\"id\": 7, \"op\": \"delete\", \"path\": \"/sdcard/DCIM/tbp/IMG_00003.jpg\"}\n"));
        assertEquals(Boolean.TRUE, ok.get("ok"));
        assertFalse(new File(folder, "IMG_00003.jpg").exists());
    }

    @Test
    public void fullStorageIsStorageFullAndTheNextCaptureWorks() {
        disk.free = ImageStore.RESERVE_BYTES + 100;
        send("{\"id\": 1, \"op\": \"capture\"}\n");
        Fakes.FakeStill still = camera.answerCapture(5000);
        agent.runPending();
        assertEquals("STORAGE_FULL", code(only(client.take())));
        assertEquals(1, still.releases);
        assertEquals(0, folder.list().length);
        disk.free = 1L << 40;
        send("{\"id\": 2, \"op\": \"capture\"}\n");
        camera.answerCapture(5000);
        agent.runPending();
        assertEquals(Boolean.TRUE, only(client.take()).get("ok"));
    }

    @Test
    public void aCameraErrorOrDisconnectIsAnsweredAndTheAgentGoesOn() {
        send("{\"id\": 1, \"op\": \"capture\"}\n");
        camera.captures.poll().failed(ErrorCode.CAPTURE_FAILED, "onCaptureFailed reason 0");
        agent.runPending();
        assertEquals("CAPTURE_FAILED", code(only(client.take())));
        send("{\"id\": 2, \"op\": \"focus\", \"diopters\": 1}\n");
        camera.focuses.poll().failed(ErrorCode.CAMERA_ERROR, "camera disconnected");
        agent.runPending();
        assertEquals("CAMERA_ERROR", code(only(client.take())));
        camera.failOnCapture = new IllegalStateException("CameraDevice was already closed");
        Map<String, Object> thrown = only(send("{\"id\": 3, \"op\": \"capture\"}\n"));
        assertEquals(3L, thrown.get("id"));
        assertEquals("CAMERA_ERROR", code(thrown));
        camera.failOnCapture = null;
        send("{\"id\": 4, \"op\": \"capture\"}\n");
        camera.answerCapture(10);
        agent.runPending();
        assertEquals(Boolean.TRUE, only(client.take()).get("ok"));
        assertAlive();
    }

    @Test
    public void aSecondAnswerFromTheCameraIsIgnored() {
        send("{\"id\": 1, \"op\": \"capture\"}\n");
        CameraBackend.Result<CameraBackend.Still> result = camera.captures.poll();
        result.failed(ErrorCode.CAMERA_ERROR, "first");
        Fakes.FakeStill late = Fakes.still(10);
        result.ok(late);
        agent.runPending();
        assertEquals("CAMERA_ERROR", code(only(client.take())));
        assertEquals(1, late.releases);
        assertEquals(1, log.errors.size());
    }

    @Test
    public void aClosedClientsWaitingOperationsAreDroppedAndItsImageIsNotWritten() {
        send("{\"id\": 1, \"op\": \"capture\"}\n{\"id\": 2, \"op\": \"focus\", \"diopters\": 1}\n");
        agent.closed(client);
        agent.runPending();
        assertTrue(client.closed);
        Fakes.FakeStill still = camera.answerCapture(100);
        agent.runPending();
        assertTrue(camera.focuses.isEmpty());
        assertEquals(0, folder.list().length);
        assertEquals(1, still.releases);
        assertTrue(client.take().isEmpty());
    }

    @Test
    public void randomBytesOnlyEverGetWellFormedAnswers() {
        Random random = new Random(31);
        String[] pieces = {"{", "}", "[", "]", "\"id\"", "\"op\"", ":", ",", "1", "-3", "2.5e3", "\"hello\"", "\"clock\"",
            "\"capture\"", "\"focus\"", "\"delete\"", "\"diopters\"", "\"path\"", "null", "true", " ", "\n", "\"\\u00e9\""};
        for (int i = 0; i < 3000; i++) {
            StringBuilder line = new StringBuilder();
            int n = random.nextInt(12);
            for (int k = 0; k < n; k++) {
                line.append(pieces[random.nextInt(pieces.length)]);
            }
            byte[] bytes = (line + "\n").getBytes(StandardCharsets.UTF_8);
            if (random.nextInt(10) == 0) {
                bytes[random.nextInt(bytes.length)] = (byte) random.nextInt(256);
            }
            sendBytes(bytes);
            while (!camera.focuses.isEmpty()) {
                camera.focuses.poll().ok(new CameraBackend.Focused(1, 1));
                agent.runPending();
            }
            while (!camera.captures.isEmpty()) {
                camera.answerCapture(10);
                agent.runPending();
            }
            for (Map<String, Object> answer : client.take()) {
                assertTrue(answer.toString(), answer.get("id") instanceof Long);
                assertTrue(answer.toString(), answer.get("ok") instanceof Boolean);
            }
        }
        assertAlive();
        assertTrue(log.errors.toString(), log.errors.isEmpty());
    }

    @Test
    public void bytesAfterTheClientClosedAreDropped() {
        agent.closed(client);
        assertTrue(send("{\"id\": 1, \"op\": \"hello\"}\n").isEmpty());
        Fakes.Client other = new Fakes.Client();
        agent.opened(other);
        byte[] hello = "{\"id\": 2, \"op\": \"hello\"}\n".getBytes(StandardCharsets.UTF_8);
        agent.received(other, hello, 0, hello.length);
        agent.runPending();
        assertEquals(2L, only(other.take()).get("id"));
    }

    @Test
    public void stopClosesTheClientsAndTheCamera() {
        agent.stop();
        agent.runPending();
        assertTrue(agent.stopping());
        agent.shutDown();
        assertTrue(client.closed);
        assertTrue(camera.closed);
    }
}
